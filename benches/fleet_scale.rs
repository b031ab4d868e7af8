//! `cargo bench --bench fleet_scale [-- N... [lan|zenoh]]`: a fleet of N emulated vehicles and
//! one ground station, all on one LAN (marea's multicast discovery) and then each vehicle reaching the
//! ground through one Zenoh router, for N = 10, 50, 100, 200 (or the N given), as JSON lines
//! `{"metric": "<lan|zenoh>.fleet<N>.<figure>", "value": ..., "unit": ...}`.
//!
//! Real nodes on real sockets in three processes (this binary re-run in a role): the vehicles
//! (N marea nodes, each publishing its position and state at 2 Hz, raising a
//! `waypoint_reached` event a second and answering `change_state`), the ground station
//! (subscribed to `*/vas/position`, `*/vas/state` and `*/vas/waypoint_reached`, calling one
//! vehicle's `change_state` a second), and for Zenoh, `usal-router`. Figures:
//!
//! - `discovery_s`: from the vehicles' process start to the ground having a position of
//!   every vehicle;
//! - `delivery_ratio`: events the ground received over those raised to it (each vehicle's
//!   sequence from its first received event; a gap or a repeat lowers it; 1.0 wanted);
//! - `telemetry_p50_ms`, `telemetry_p99_ms`: position age at the ground (same host clock);
//! - `calls_ok_ratio`: the ground's calls answered, over those answered or failed (one still
//!   in flight when the window closes is neither);
//! - `ground_cpu_percent`, `router_cpu_percent`, `vehicle_cpu_percent` (the vehicles'
//!   process over N), in percent of one core over the window;
//! - `discovery_bytes_per_s` (LAN): bytes on the discovery multicast group, counted by a
//!   socket of this bench; `ground_bytes_per_s`: bytes in and out of the ground's link;
//! - `ground_rss_kib`, `vehicle_rss_kib` (the vehicles' process over N).
//!
//! `FS_LOG=marea=info` (a tracing filter) has the vehicles' process log on stderr: which peers
//! its nodes dropped and why.

use std::collections::HashMap;
use std::io::BufRead;
use std::net::{Ipv4Addr, SocketAddrV4, UdpSocket};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{mpsc, Arc};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::{bail, Context};
use serde::{Deserialize, Serialize};
use serde_json::json;

/// After every vehicle is discovered, before the window.
const WARMUP: Duration = Duration::from_secs(5);
/// The measurement window.
const WINDOW: Duration = Duration::from_secs(20);
/// The kernel's clock ticks per second in `/proc`.
const TICKS: f64 = 100.0;

/// A vehicle's position sample: its sequence and when it was sent.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
struct Fix {
    seq: u64,
    sent_us: u64,
    lat: f64,
    lon: f64,
}

fn now_us() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_micros() as u64)
}

fn out(v: serde_json::Value) {
    use std::io::Write;
    let mut s = std::io::stdout().lock();
    let _ = writeln!(s, "{v}");
    let _ = s.flush();
}

fn metric(name: &str, value: f64, unit: &str) {
    out(json!({"metric": name, "value": value, "unit": unit}));
}

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    match args.first().map(String::as_str) {
        Some("--role-vehicles") => {
            if std::env::var("FS_LOG").is_ok() {
                tracing_subscriber::fmt()
                    .with_env_filter(tracing_subscriber::EnvFilter::from_env("FS_LOG"))
                    .with_writer(std::io::stderr)
                    .init();
            }
            roles(vehicles(&args[1..]))
        }
        Some("--role-ground") => roles(ground(&args[1..])),
        _ => {
            let ns: Vec<usize> = args.iter().filter_map(|a| a.parse().ok()).collect();
            let ns = if ns.is_empty() {
                vec![10, 50, 100, 200]
            } else {
                ns
            };
            // `lan` or `zenoh` among the arguments: that mode only.
            let named = |z: bool| args.iter().any(|a| a == mode(z));
            let modes: Vec<bool> = [false, true]
                .into_iter()
                .filter(|&z| named(z) || !named(!z))
                .collect();
            for n in ns {
                for &zenoh in &modes {
                    if let Err(e) = run(n, zenoh) {
                        eprintln!("fleet_scale: N={n} {}: {e:#}", mode(zenoh));
                    }
                }
            }
            Ok(())
        }
    }
}

fn mode(zenoh: bool) -> &'static str {
    if zenoh {
        "zenoh"
    } else {
        "lan"
    }
}

fn roles(f: impl std::future::Future<Output = anyhow::Result<()>>) -> anyhow::Result<()> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?
        .block_on(f)
}

/// `--role-vehicles N CONFIG`: N vehicle nodes from the template network file.
async fn vehicles(args: &[String]) -> anyhow::Result<()> {
    let n: usize = args.first().context("N")?.parse()?;
    let template = marea::NetworkConfig::load(args.get(1).context("CONFIG")?)?;
    let mut nodes = Vec::new();
    for i in 0..n {
        let mut c = template.clone();
        c.node = format!("v{i}");
        c.namespace = Some(format!("v{i}"));
        nodes.push(marea::Node::open(&c).await.context("opening a vehicle")?);
    }
    let raised = Arc::new(AtomicU64::new(0));
    let mut keep = Vec::new();
    for (i, node) in nodes.iter().enumerate() {
        let svc = node.service("vas")?;
        let pos = svc.publish_variable::<Fix>("position")?;
        let state = svc.publish_variable::<u8>("state")?;
        let ev = svc.publish_event::<u64>("waypoint_reached")?;
        let f = svc.provide_function("change_state", |s: u8| async move { Ok::<u8, String>(s) })?;
        let raised = raised.clone();
        // Spread over the half second so the fleet does not publish in one burst.
        let offset = Duration::from_millis((i as u64 * 500) / n.max(1) as u64);
        keep.push((svc, f));
        tokio::spawn(async move {
            tokio::time::sleep(offset).await;
            let mut tick = tokio::time::interval(Duration::from_millis(500));
            let mut seq = 0u64;
            loop {
                tick.tick().await;
                let _ = pos.set(&Fix {
                    seq,
                    sent_us: now_us(),
                    lat: 41.0 + i as f64 * 1e-4,
                    lon: 2.0 + seq as f64 * 1e-6,
                });
                let _ = state.set(&3);
                if seq % 2 == 0 && ev.raise_nowait(&(seq / 2)).is_ok() {
                    raised.fetch_add(1, Ordering::Relaxed);
                }
                seq += 1;
            }
        });
    }
    out(json!({"ready": n}));
    // Every 10 s, the vehicles' links summed, on stderr: what their sessions went through.
    let nodes = Arc::new(nodes);
    let watched = nodes.clone();
    tokio::spawn(async move {
        loop {
            tokio::time::sleep(Duration::from_secs(10)).await;
            let mut t = marea::link::LinkStats::default();
            for node in watched.iter() {
                for (_, s) in node.link_stats() {
                    t.sessions_expired += s.sessions_expired;
                    t.sessions_given_up += s.sessions_given_up;
                    t.retransmitted += s.retransmitted;
                    t.fast_dropped += s.fast_dropped;
                }
            }
            eprintln!(
                "fleet_scale vehicles: sessions expired {}, given up {}; retransmitted {}; fast dropped {}",
                t.sessions_expired, t.sessions_given_up, t.retransmitted, t.fast_dropped
            );
        }
    });
    marea::process::terminated().await;
    out(json!({"raised": raised.load(Ordering::Relaxed)}));
    Ok(())
}

/// `--role-ground N CONFIG`: follows the fleet; prints `discovered`, `window_start`, `result`.
async fn ground(args: &[String]) -> anyhow::Result<()> {
    let n: usize = args.first().context("N")?.parse()?;
    let config = marea::NetworkConfig::load(args.get(1).context("CONFIG")?)?;
    let started = Instant::now();
    let node = marea::Node::open(&config).await?;
    let svc = node.service("station")?;
    let positions = svc.subscribe_variable::<Fix>("*/vas/position")?;
    let _states = svc.subscribe_variable::<u8>("*/vas/state")?;
    let events = svc.subscribe_event::<u64>("*/vas/waypoint_reached")?;
    // Events: per vehicle, the first sequence received and every one after it.
    let mut seqs: HashMap<String, (u64, u64, u64)> = HashMap::new(); // first, last, count
    let mut dups = 0u64;
    let mut seen: HashMap<String, ()> = HashMap::new();
    while seen.len() < n {
        let s = positions.recv().await?;
        seen.insert(s.publisher.to_string(), ());
    }
    out(json!({"discovered": n, "ms": started.elapsed().as_millis() as u64}));
    let warm_end = Instant::now() + WARMUP;
    let mut latencies: Vec<f64> = Vec::new();
    let mut window: Option<Instant> = None;
    let calls = Arc::new(AtomicU64::new(0));
    let calls_ok = Arc::new(AtomicU64::new(0));
    let link_bytes = |node: &marea::Node| -> u64 {
        node.link_stats()
            .iter()
            .map(|(_, s)| s.bytes_in + s.bytes_out)
            .sum()
    };
    let mut bytes0 = 0u64;
    loop {
        let now = Instant::now();
        if window.is_none() && now >= warm_end {
            window = Some(now);
            bytes0 = link_bytes(&node);
            out(json!({"window_start": true}));
            // A call a second, each to the next vehicle, beside the subscriptions.
            let (svc, calls, calls_ok) = (node.service("caller")?, calls.clone(), calls_ok.clone());
            tokio::spawn(async move {
                let mut tick = tokio::time::interval(Duration::from_secs(1));
                for i in 0.. {
                    tick.tick().await;
                    let Ok(f) = svc.function::<u8, u8>(&format!("v{}/vas/change_state", i % n))
                    else {
                        break;
                    };
                    // Counted once answered or failed: one still in flight when the window
                    // closes is neither.
                    let outcome = f.call(&4, Duration::from_secs(2)).await;
                    calls.fetch_add(1, Ordering::Relaxed);
                    match outcome {
                        Ok(4) => {
                            calls_ok.fetch_add(1, Ordering::Relaxed);
                        }
                        // Why a call failed, for the report (stderr).
                        other => eprintln!("fleet_scale ground: call {i}: {other:?}"),
                    }
                }
            });
        }
        if window.is_some_and(|w| now >= w + WINDOW) {
            break;
        }
        tokio::select! {
            s = positions.recv() => {
                let s = s?;
                if window.is_some() {
                    latencies.push(now_us().saturating_sub(s.value.sent_us) as f64 / 1000.0);
                }
            }
            e = events.recv() => {
                let e = e?;
                let entry = seqs.entry(e.publisher.to_string()).or_insert((e.value, e.value.wrapping_sub(1), 0));
                if e.value <= entry.1 && entry.2 > 0 {
                    dups += 1;
                } else {
                    entry.1 = e.value;
                    entry.2 += 1;
                }
            }
            _ = tokio::time::sleep(Duration::from_millis(50)) => {}
        }
    }
    latencies.sort_by(f64::total_cmp);
    let pct = |p: f64| -> f64 {
        if latencies.is_empty() {
            return f64::NAN;
        }
        latencies[((latencies.len() - 1) as f64 * p).round() as usize]
    };
    let received: u64 = seqs.values().map(|s| s.2).sum();
    let expected: u64 = seqs.values().map(|s| s.1 - s.0 + 1).sum();
    out(json!({"result": {
        "received": received, "expected": expected, "duplicates": dups,
        "p50_ms": pct(0.5), "p99_ms": pct(0.99), "samples": latencies.len(),
        "calls": calls.load(Ordering::Relaxed), "calls_ok": calls_ok.load(Ordering::Relaxed),
        "link_bytes": link_bytes(&node) - bytes0,
        // Its own: the runner may find the process gone once it printed this.
        "rss_kib": rss_kib(std::process::id()),
    }}));
    drop(svc);
    node.shutdown().await;
    Ok(())
}

/// A child process, killed on drop.
struct Proc {
    child: Child,
    lines: mpsc::Receiver<serde_json::Value>,
}

impl Proc {
    fn spawn(args: &[String]) -> anyhow::Result<Proc> {
        let mut child = Command::new(std::env::current_exe()?)
            .args(args)
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()?;
        Self::reading(child.stdout.take().context("stdout")?, child)
    }

    fn reading(stdout: std::process::ChildStdout, child: Child) -> anyhow::Result<Proc> {
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in std::io::BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                if let Ok(v) = serde_json::from_str(&line) {
                    if tx.send(v).is_err() {
                        break;
                    }
                }
            }
        });
        Ok(Proc { child, lines: rx })
    }

    fn expect(&self, key: &str, within: Duration) -> anyhow::Result<serde_json::Value> {
        let deadline = Instant::now() + within;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(v) if v.get(key).is_some() => return Ok(v),
                Ok(_) => {}
                Err(_) => bail!("no `{key}` within {within:?}"),
            }
        }
    }

    fn pid(&self) -> u32 {
        self.child.id()
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// CPU ticks (user + system) of `pid`.
fn cpu_ticks(pid: u32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .ok()
        .and_then(|s| {
            let rest = s.rsplit_once(')')?.1.to_owned();
            let f: Vec<&str> = rest.split_whitespace().collect();
            Some(f.get(11)?.parse::<u64>().ok()? + f.get(12)?.parse::<u64>().ok()?)
        })
        .unwrap_or(0)
}

/// Resident memory of `pid`, KiB.
fn rss_kib(pid: u32) -> u64 {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("VmRSS:"))?
                .split_whitespace()
                .nth(1)?
                .parse()
                .ok()
        })
        .unwrap_or(0)
}

fn free_port() -> anyhow::Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}

/// The release `usal-router`, built once per bench run (cargo: a no-op when fresh).
fn router_binary() -> anyhow::Result<PathBuf> {
    static BUILT: std::sync::OnceLock<PathBuf> = std::sync::OnceLock::new();
    if let Some(p) = BUILT.get() {
        return Ok(p.clone());
    }
    let p = build_router()?;
    Ok(BUILT.get_or_init(|| p).clone())
}

fn build_router() -> anyhow::Result<PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let status = Command::new(env!("CARGO"))
        .args(["build", "--release", "-p", "usal-router"])
        .current_dir(root)
        .status()
        .context("building usal-router")?;
    if !status.success() {
        bail!("building usal-router failed");
    }
    let target = std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| root.join("target"));
    Ok(target.join("release/usal-router"))
}

fn run(n: usize, zenoh: bool) -> anyhow::Result<()> {
    let dir = tempfile::tempdir()?;
    let domain = format!("fleet-scale-{n}-{}", std::process::id());
    let mcast_port = free_port()?;
    let mut router = None;
    let link = if zenoh {
        let port = free_port()?;
        let mut child = Command::new(router_binary()?)
            .args(["--json", "--listen", &format!("tcp/127.0.0.1:{port}")])
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .context("starting usal-router")?;
        let stdout = child.stdout.take().context("router stdout")?;
        let r = Proc::reading(stdout, child)?;
        r.expect("event", Duration::from_secs(30))?;
        router = Some(r);
        format!(r#"<zenoh mode="client" connect="tcp/127.0.0.1:{port}"/>"#)
    } else {
        format!(
            r#"<ethernet bind="127.0.0.1:0" multicast="239.255.77.1:{mcast_port}" interface="127.0.0.1"/>"#
        )
    };
    let write = |name: &str| -> anyhow::Result<String> {
        let p = dir.path().join(format!("{name}.xml"));
        std::fs::write(
            &p,
            format!(r#"<network node="{name}" domain="{domain}">{link}</network>"#),
        )?;
        Ok(p.display().to_string())
    };
    let ground_cfg = write("ground")?;
    let vehicles_cfg = write("template")?;

    // The discovery group's bytes (LAN), counted from the start.
    let counting = Arc::new(AtomicBool::new(true));
    let group_bytes = Arc::new(AtomicU64::new(0));
    if !zenoh {
        let sock = socket2::Socket::new(
            socket2::Domain::IPV4,
            socket2::Type::DGRAM,
            Some(socket2::Protocol::UDP),
        )?;
        sock.set_reuse_address(true)?;
        sock.bind(&SocketAddrV4::new(Ipv4Addr::new(239, 255, 77, 1), mcast_port).into())?;
        sock.join_multicast_v4(&Ipv4Addr::new(239, 255, 77, 1), &Ipv4Addr::LOCALHOST)?;
        let sock: UdpSocket = sock.into();
        sock.set_read_timeout(Some(Duration::from_millis(200)))?;
        let (counting, bytes) = (counting.clone(), group_bytes.clone());
        std::thread::spawn(move || {
            let mut buf = [0u8; 65_536];
            while counting.load(Ordering::Relaxed) {
                if let Ok(k) = sock.recv(&mut buf) {
                    bytes.fetch_add(k as u64, Ordering::Relaxed);
                }
            }
        });
    }

    let ground = Proc::spawn(&["--role-ground".into(), n.to_string(), ground_cfg])?;
    let started = Instant::now();
    let fleet = Proc::spawn(&["--role-vehicles".into(), n.to_string(), vehicles_cfg])?;
    let discovered = ground.expect("discovered", Duration::from_secs(300))?;
    let discovery_s = started.elapsed().as_secs_f64();
    ground.expect("window_start", WARMUP + Duration::from_secs(30))?;
    let t0 = Instant::now();
    let pids: Vec<u32> = [
        Some(ground.pid()),
        router.as_ref().map(Proc::pid),
        Some(fleet.pid()),
    ]
    .into_iter()
    .flatten()
    .collect();
    let cpu0: Vec<u64> = pids.iter().map(|p| cpu_ticks(*p)).collect();
    let g0 = group_bytes.load(Ordering::Relaxed);
    let result = ground.expect("result", WINDOW + Duration::from_secs(60))?;
    let secs = t0.elapsed().as_secs_f64();
    let cpu: Vec<f64> = pids
        .iter()
        .zip(&cpu0)
        .map(|(p, c0)| (cpu_ticks(*p) - c0) as f64 / TICKS / secs * 100.0)
        .collect();
    let g1 = group_bytes.load(Ordering::Relaxed);
    counting.store(false, Ordering::Relaxed);
    let fleet_rss = rss_kib(fleet.pid());

    let m = |k: &str| format!("{}.fleet{n}.{k}", mode(zenoh));
    let r = &result["result"];
    let f = |k: &str| r[k].as_f64().unwrap_or(f64::NAN);
    metric(&m("discovery_s"), discovery_s, "s");
    let expected = f("expected");
    metric(
        &m("delivery_ratio"),
        if expected > 0.0 {
            (f("received") - f("duplicates")) / expected
        } else {
            f64::NAN
        },
        "ratio",
    );
    metric(&m("telemetry_p50_ms"), f("p50_ms"), "ms");
    metric(&m("telemetry_p99_ms"), f("p99_ms"), "ms");
    metric(
        &m("calls_ok_ratio"),
        f("calls_ok") / f("calls").max(1.0),
        "ratio",
    );
    metric(&m("ground_cpu_percent"), cpu[0], "%");
    if zenoh {
        metric(&m("router_cpu_percent"), cpu[1], "%");
    } else {
        metric(&m("discovery_bytes_per_s"), (g1 - g0) as f64 / secs, "B/s");
    }
    metric(
        &m("vehicle_cpu_percent"),
        cpu[cpu.len() - 1] / n as f64,
        "%",
    );
    metric(&m("ground_bytes_per_s"), f("link_bytes") / secs, "B/s");
    metric(&m("ground_rss_kib"), f("rss_kib"), "KiB");
    metric(&m("vehicle_rss_kib"), fleet_rss as f64 / n as f64, "KiB");
    eprintln!(
        "fleet_scale {} N={n}: discovered {discovered} in {discovery_s:.1} s; {r}",
        mode(zenoh)
    );
    Ok(())
}
