//! marea as a user would use it: `Variable<Vec<u8>>` for round trips and the lossy rate,
//! `Event<Vec<u8>>` through its lossless stream (`Event::stream`) for the reliable rate, both
//! received through callbacks (`subscribe_*_with`), as the Zenoh peer receives. LINK is
//! `udp:PORT` (loopback, discovery multicast on PORT), `shm` (iceoryx2, `wait="event"`) or
//! `serial:DEV:BAUD` (one end of a pty pair the runner bridges). KEY is the domain (and the shm
//! service name), `DOMAIN/NODE` to name the node (a fan-out's subscribers, an idle partner).
//! Roles `pub`/`sub` take a suffix: `pub-event`, `pub-var`, `sub-event`, `sub-var`, and
//! `pub-api`/`sub-api`: events as services use them, `raise_nowait` with up to
//! [`IN_FLIGHT`] in flight and `recv().await` on a task, on the multi-thread runtime
//! `#[tokio::main]` gives (built into `peer-marea` only, with marea's default features).
//!
//! Built three times from this file, each as a node for its link would be built: `peer-marea`
//! (package `peers`, marea's default features) for the serial cases, `peer-marea-udp` (package
//! `marea-udp`, marea's feature `udp` alone) for the UDP ones and `peer-marea-shm` (package
//! `marea-shm`, feature `shm` alone) for the shm ones; given a link
//! its build lacks, a peer fails to open its node.

use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context};
use marea::config::{EthernetConfig, LinkConfig, ShmConfig};
use marea::{NetworkConfig, Node};
use peers_common::{
    finish_sub, payload, ready, seq, subscribers, timed_round_trips, under_load, Args, Arrivals,
    BulkMeter, Control, Rtts, BULK_FRAME,
};

fn config(node: &str, key: &str, link: &str) -> anyhow::Result<NetworkConfig> {
    if let Some(rest) = link.strip_prefix("serial:") {
        let (dev, baud) = rest
            .rsplit_once(':')
            .ok_or_else(|| anyhow!("LINK {link:?}: expected serial:DEV:BAUD"))?;
        let xml = format!(
            r#"<network node="{node}" domain="{key}"><serial name="radio" address="{dev}" baudRate="{baud}" heartbeatMs="1000"/></network>"#
        );
        return NetworkConfig::parse(&xml, None).map_err(|e| anyhow!("serial config: {e}"));
    }
    let mut c = NetworkConfig::ethernet_loopback(node);
    c.domain = key.to_owned();
    if let Some(port) = link.strip_prefix("udp:") {
        let port: u16 = port.parse().with_context(|| format!("LINK {link:?}"))?;
        c.links = vec![LinkConfig::Ethernet(EthernetConfig {
            interface: std::net::Ipv4Addr::LOCALHOST,
            bind: "127.0.0.1:0".parse().expect("literal address"),
            multicast: std::net::SocketAddrV4::new(std::net::Ipv4Addr::new(239, 255, 77, 17), port),
            ..EthernetConfig::default()
        })];
    } else if link == "shm" {
        c.links = vec![LinkConfig::Shm(ShmConfig {
            service: key.to_owned(),
            // A fan-out's publisher and subscribers all meet on the one link.
            max_peers: ShmConfig::default().max_peers.max(subscribers() + 1),
            ..ShmConfig::default()
        })];
    } else {
        anyhow::bail!("LINK {link:?}: expected udp:PORT, shm or serial:DEV:BAUD");
    }
    Ok(c)
}

fn main() -> anyhow::Result<()> {
    let args = Args::parse()?;
    let control = Control::start(false);
    // A current-thread runtime, the leanest tokio offers: marea's tasks (links, discovery,
    // dispatch) share the one thread with the role's, and the build links no multi-thread
    // scheduler (the UDP and shm peers' tokio has no `rt-multi-thread`: see their Cargo.toml).
    // The `-api` and `-load` roles run on the multi-thread runtime services get from
    // `#[tokio::main]` (under load, the bulk stream and the calls on their own workers, as
    // Zenoh's peer has its own threads).
    let rt = if args.role.ends_with("-api") || args.role.ends_with("-load") {
        multi_thread_runtime()?
    } else {
        tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()
            .context("tokio runtime")?
    };
    // Behind `dyn`: `block_on` inlines a concrete future into each of its paths (with
    // `rt-multi-thread`, as `peer-marea` is built: current-thread, multi-thread and entering
    // the runtime), which made three copies of this peer's 25 KB state machine (75 KB of code,
    // all of it resident).
    let main: std::pin::Pin<Box<dyn std::future::Future<Output = anyhow::Result<()>>>> =
        Box::pin(run(args, control));
    rt.block_on(main)
}

#[cfg(feature = "multi-thread")]
fn multi_thread_runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    tokio::runtime::Runtime::new().context("tokio runtime")
}

#[cfg(not(feature = "multi-thread"))]
fn multi_thread_runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    anyhow::bail!("this build of the marea peer has no multi-thread runtime: the -api roles run in peer-marea")
}

const MATCH: Duration = Duration::from_secs(20);

/// Events a `pub-api` keeps in flight (raised, report not awaited yet).
const IN_FLIGHT: usize = 4096;
/// Frames a `pub-blob` keeps in flight.
const BLOBS_IN_FLIGHT: usize = 3;

/// The publisher's event `d`, once every subscriber of the run matched it (all of a fan-out's);
/// then tells the runner it is ready.
async fn matched_event(svc: &marea::Service) -> anyhow::Result<marea::Event<Vec<u8>>> {
    matched_event_named(svc, "d").await
}

/// [`matched_event`] for the event `name`.
async fn matched_event_named(
    svc: &marea::Service,
    name: &str,
) -> anyhow::Result<marea::Event<Vec<u8>>> {
    let ev = svc.publish_event::<Vec<u8>>(name)?;
    let n = subscribers();
    if !ev.wait_remote_subscribers(n, MATCH).await {
        anyhow::bail!("pub: not {n} subscribers of {name} within {MATCH:?}");
    }
    ready("");
    Ok(ev)
}

async fn run(args: Args, control: Arc<Control>) -> anyhow::Result<()> {
    let link = args.link.clone().context("LINK missing")?;
    let base = args.role.split('-').next().unwrap_or("x");
    let (domain, node_name) = args
        .key
        .split_once('/')
        .unwrap_or((args.key.as_str(), base));
    let node = Node::open(&config(node_name, domain, &link)?)
        .await
        .map_err(|e| anyhow!("open node {node_name} on {link}: {e}"))?;
    let svc = node
        .service(node_name)
        .map_err(|e| anyhow!("service: {e}"))?;
    let result = async {
        match args.role.as_str() {
            "pong" => {
                let pings = svc.subscribe_variable::<Vec<u8>>("ping/v")?;
                let pong = svc.publish_variable::<Vec<u8>>("v")?;
                // The ping starts once this is ready; it makes sure both directions match.
                ready("");
                while !control.closed() {
                    if let Ok(s) = pings.recv_timeout(Duration::from_millis(200)).await {
                        pong.set(&s.value)?;
                    }
                }
            }
            "ping" => {
                let pongs = svc.subscribe_variable::<Vec<u8>>("pong/v")?;
                let ping = svc.publish_variable::<Vec<u8>>("v")?;
                if !ping.wait_remote_subscribers(1, MATCH).await {
                    anyhow::bail!("ping: no subscriber within {MATCH:?}");
                }
                // Both directions matched: a pong came back (values sent before the pong's
                // publisher knew of this subscriber are lost, so ask again until one comes).
                let end = Instant::now() + MATCH;
                'hello: loop {
                    if Instant::now() > end {
                        anyhow::bail!("ping: no pong within {MATCH:?}");
                    }
                    ping.set(&payload(args.size, u64::MAX))?;
                    while let Ok(s) = pongs.recv_timeout(Duration::from_millis(50)).await {
                        if seq(&s.value) == Some(u64::MAX) {
                            break 'hello;
                        }
                    }
                }
                ready("");
                let mut rtts = Rtts::new(args.param as usize);
                for i in 0..rtts.total() as u64 {
                    let t = Instant::now();
                    ping.set(&payload(args.size, i))?;
                    // Best effort: a lost value (rare) times out and the next one goes.
                    let end = t + Duration::from_secs(2);
                    loop {
                        let left = end.saturating_duration_since(Instant::now());
                        match pongs.recv_timeout(left).await {
                            Ok(s) if seq(&s.value) == Some(i) => {
                                rtts.push(t);
                                break;
                            }
                            Ok(_) => {}
                            Err(_) => break,
                        }
                    }
                }
                rtts.finish();
            }
            "pong-load" => {
                // Commands are calls: the round trip is one, answered with its argument.
                let _echo = svc.provide_function("echo", |x: Vec<u8>| async move {
                    Ok::<Vec<u8>, String>(x)
                })?;
                let _bulk = svc.subscribe_event_with::<Vec<u8>, _>("ping/bulk", |_| {})?;
                ready("");
                while !control.closed() {
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
            }
            "ping-load" => {
                let echo = svc.function::<Vec<u8>, Vec<u8>>("pong/echo")?;
                if !echo.wait_provider(MATCH).await {
                    anyhow::bail!("ping-load: no echo provider within {MATCH:?}");
                }
                let bulk = matched_event_named(&svc, "bulk").await?;
                let mut call = |i: u64| {
                    let echo = &echo;
                    async move {
                        let t = Instant::now();
                        let back = echo.call(&payload(args.size, i), Duration::from_secs(5)).await;
                        match back {
                            Ok(v) if seq(&v) == Some(i) => Ok(t),
                            Ok(_) => Err(anyhow!("ping-load: call {i} answered another's bytes")),
                            Err(e) => Err(anyhow!("ping-load: call {i}: {e}")),
                        }
                    }
                };
                let idle = timed_round_trips(args.param as usize, 0, &mut call)
                    .await?
                    .percentiles();
                // The bulk stream, lossless with back-pressure, on a task of its own.
                let meter = Arc::new(BulkMeter::default());
                let m = meter.clone();
                let streamer = tokio::spawn(async move {
                    let frame = payload(BULK_FRAME, 0);
                    let mut stream = bulk.stream();
                    while !m.stopped() {
                        stream.send(&frame).await?;
                        m.add(frame.len());
                    }
                    Ok::<_, anyhow::Error>(())
                });
                under_load(args.param as usize, idle, &meter, streamer, call).await?;
            }
            "sub-event" | "sub-var" => {
                let arrivals = Arc::new(Arrivals::default());
                let a = arrivals.clone();
                // Through a callback, as the Zenoh peer's subscriber takes them: each counted
                // on the link's receive task, no hand-off to a reading task.
                let count = move |s: Result<_, _>| {
                    if s.is_ok() {
                        a.add();
                    }
                };
                let sub = if args.role == "sub-event" {
                    svc.subscribe_event_with::<Vec<u8>, _>("pub/d", count)?
                } else {
                    svc.subscribe_variable_with::<Vec<u8>, _>("pub/d", count)?
                };
                ready("");
                let c = control.clone();
                tokio::task::spawn_blocking(move || finish_sub(&arrivals, &c)).await?;
                drop(sub);
            }
            "sub-blob" => {
                // Frames received as views of shared memory, counted and released in the
                // callback (as the iceoryx2 peer's subscriber does with its samples).
                let arrivals = Arc::new(Arrivals::default());
                let a = arrivals.clone();
                let sub = svc.subscribe_event_with::<marea::Blob, _>("pub/d", move |s| {
                    if s.is_ok() {
                        a.add();
                    }
                })?;
                ready("");
                let c = control.clone();
                tokio::task::spawn_blocking(move || finish_sub(&arrivals, &c)).await?;
                drop(sub);
            }
            "pub-blob" => {
                // Each frame written once, into the subscriber's shared memory when it is
                // lent; a few raised and not yet acknowledged, as a camera pipeline keeps.
                let ev = svc.publish_event::<marea::Blob>("d")?;
                if !ev.wait_remote_subscribers(subscribers(), MATCH).await {
                    anyhow::bail!("pub: no subscriber of d within {MATCH:?}");
                }
                ready("");
                let frame = payload(args.size, 0);
                let (start, mut sent, mut lent) = (Instant::now(), 0u64, 0u64);
                let mut in_flight = std::collections::VecDeque::with_capacity(BLOBS_IN_FLIGHT);
                while start.elapsed().as_secs_f64() < args.param {
                    if in_flight.len() >= BLOBS_IN_FLIGHT {
                        if let Some(oldest) = in_flight.pop_front() {
                            let _ = oldest.await;
                        }
                    }
                    let mut loan = ev.loan(frame.len())?;
                    lent += u64::from(loan.is_shared_memory());
                    loan.append(&frame);
                    in_flight.push_back(loan.raise_nowait());
                    sent += 1;
                }
                let secs = start.elapsed().as_secs_f64();
                for p in in_flight {
                    let _ = tokio::time::timeout(Duration::from_secs(30), p).await;
                }
                if lent < sent {
                    eprintln!("peer-marea: {} of {sent} frames were not lent shared memory", sent - lent);
                }
                println!("result {sent} {secs}");
            }
            "sub-api" => {
                let arrivals = Arc::new(Arrivals::default());
                let a = arrivals.clone();
                let sub = svc.subscribe_event::<Vec<u8>>("pub/d")?;
                let reader = tokio::spawn(async move {
                    while sub.recv().await.is_ok() {
                        a.add();
                    }
                });
                ready("");
                let c = control.clone();
                tokio::task::spawn_blocking(move || finish_sub(&arrivals, &c)).await?;
                reader.abort();
            }
            "pub-api" => {
                let ev = matched_event(&svc).await?;
                let msg = payload(args.size, 0);
                let start = Instant::now();
                let mut sent = 0u64;
                let mut in_flight = std::collections::VecDeque::with_capacity(IN_FLIGHT);
                while start.elapsed().as_secs_f64() < args.param {
                    for _ in 0..64 {
                        if in_flight.len() >= IN_FLIGHT {
                            if let Some(oldest) = in_flight.pop_front() {
                                let _ = oldest.await;
                            }
                        }
                        in_flight.push_back(ev.raise_nowait(&msg)?);
                        sent += 1;
                    }
                }
                let secs = start.elapsed().as_secs_f64();
                let all = async {
                    for p in in_flight {
                        let _ = p.await;
                    }
                };
                if tokio::time::timeout(Duration::from_secs(30), all)
                    .await
                    .is_err()
                {
                    eprintln!("peer-marea: events still unreported 30 s after the last one");
                }
                println!("result {sent} {secs}");
            }
            "pub-event" => {
                let ev = matched_event(&svc).await?;
                let msg = payload(args.size, 0);
                let start = Instant::now();
                let mut sent = 0u64;
                // The lossless stream: back-pressure when a subscriber is STREAM_WINDOW events
                // behind, no report per event. The clock is read every 64 messages, as the other
                // peers' publishers do.
                let mut stream = ev.stream();
                while start.elapsed().as_secs_f64() < args.param {
                    for _ in 0..64 {
                        stream.send(&msg).await?;
                        sent += 1;
                    }
                }
                let secs = start.elapsed().as_secs_f64();
                if tokio::time::timeout(Duration::from_secs(30), stream.flush())
                    .await
                    .is_err()
                {
                    eprintln!("peer-marea: events still unacknowledged 30 s after the last one");
                }
                println!("result {sent} {secs}");
            }
            "pub-var" => {
                let var = svc.publish_variable::<Vec<u8>>("d")?;
                if !var.wait_remote_subscribers(1, MATCH).await {
                    anyhow::bail!("pub: no subscriber within {MATCH:?}");
                }
                ready("");
                let msg = payload(args.size, 0);
                let start = Instant::now();
                let mut sent = 0u64;
                while start.elapsed().as_secs_f64() < args.param {
                    for _ in 0..64 {
                        var.set(&msg)?;
                        sent += 1;
                    }
                    tokio::task::yield_now().await;
                }
                println!("result {sent} {}", start.elapsed().as_secs_f64());
            }
            "idle" => {
                ready("");
                while !control.closed() {
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
            }
            other => anyhow::bail!("unknown role {other:?}"),
        }
        Ok(())
    }
    .await;
    drop(svc);
    let _ = tokio::time::timeout(Duration::from_secs(5), node.shutdown()).await;
    result
}
