//! `marea-probe`: a small node driven from the command line, printing what it sees as JSON
//! lines on stdout. The cross-process tests and the demo use it; users can use it to poke at a
//! running system (publish a value, follow an event, call a function, send a file).

use std::path::PathBuf;
use std::time::{Duration, Instant};

use anyhow::{bail, Context};
use clap::{Parser, Subcommand};
use marea::config::{EthernetConfig, LinkConfig};
use marea::{NetworkConfig, Node, SendFileOptions};
use serde::{Deserialize, Serialize};
use serde_json::json;

/// A position sample as the VAS publishes it: 3×f64 + 2×f32 = 32 bytes of payload.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
struct Position {
    lat: f64,
    lon: f64,
    alt: f64,
    heading: f32,
    speed: f32,
}

#[derive(Parser)]
#[command(about = "A scriptable marea node for tests and demos")]
struct Args {
    /// Node name.
    #[arg(long, default_value = "probe")]
    node: String,
    /// Namespace prefixing this node's items.
    #[arg(long)]
    namespace: Option<String>,
    /// Discovery domain (nodes of other domains are ignored).
    #[arg(long, default_value = "usal")]
    domain: String,
    /// network.xml to load instead of the loopback defaults below.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Multicast port for discovery on 127.0.0.1.
    #[arg(long, default_value_t = 7477)]
    mcast_port: u16,
    /// Heartbeat period in ms.
    #[arg(long, default_value_t = 1000)]
    heartbeat_ms: u64,
    /// Lease in ms.
    #[arg(long, default_value_t = 3500)]
    lease_ms: u64,
    /// Service name for this probe's items.
    #[arg(long, default_value = "probe")]
    service: String,
    /// Domain key file: authenticate every link with it (as <security keyFile=".."/>).
    #[arg(long)]
    key_file: Option<PathBuf>,
    /// With --key-file: encrypt serial links too (as encrypt="radio").
    #[arg(long)]
    encrypt_radio: bool,
    /// With --key-file: this node's identity key (as identityFile="..").
    #[arg(long)]
    identity_file: Option<PathBuf>,
    /// With --key-file: the domain's identities.xml (as identities="..").
    #[arg(long)]
    identities: Option<PathBuf>,
    #[command(subcommand)]
    cmd: Cmd,
}

#[derive(Subcommand)]
enum Cmd {
    /// Publish positions on ITEM: COUNT values every INTERVAL ms, then keep serving the last.
    VarPub {
        #[arg(long)]
        item: String,
        #[arg(long, default_value_t = 1)]
        count: u64,
        #[arg(long, default_value_t = 0)]
        interval_ms: u64,
        /// Publish the VAS's position type (`usal_types::Position`, which the tools and the
        /// Zenoh bridge show as JSON) instead of the probe's own 32-byte one.
        #[arg(long)]
        usal_type: bool,
    },
    /// Print positions matching PATTERN; exit after COUNT (0 = run until stopped).
    VarSub {
        #[arg(long)]
        pattern: String,
        #[arg(long, default_value_t = 0)]
        count: u64,
    },
    /// Print link-health values (`marea::LinkHealth`) matching PATTERN; exit after COUNT.
    Health {
        #[arg(long)]
        pattern: String,
        #[arg(long, default_value_t = 1)]
        count: u64,
    },
    /// Subscribe to PATTERN expecting strings, to show a type refusal.
    VarSubString {
        #[arg(long)]
        pattern: String,
    },
    /// Raise COUNT events (u64 sequence numbers) on ITEM once SUBS remote nodes subscribe.
    EvPub {
        #[arg(long)]
        item: String,
        #[arg(long)]
        count: u64,
        #[arg(long, default_value_t = 1)]
        subs: usize,
        /// Events in flight.
        #[arg(long, default_value_t = 256)]
        window: usize,
        /// Pause between events in ms.
        #[arg(long, default_value_t = 0)]
        interval_ms: u64,
        /// Send through a lossless stream (`Event::stream`: back-pressure, no report per event,
        /// losses reported by node) instead of `raise_nowait` with WINDOW in flight.
        #[arg(long)]
        stream: bool,
    },
    /// Receive events on PATTERN and check each publisher's sequence; exit after COUNT.
    EvSub {
        #[arg(long)]
        pattern: String,
        #[arg(long)]
        count: u64,
        /// Accept any first sequence number per publisher (a subscriber started mid-stream).
        #[arg(long)]
        from_any: bool,
        /// Pause a millisecond after every SLOW events: a reader slower than its publisher
        /// (says `{"behind": N}` once N events wait, over a quarter of its mailbox).
        #[arg(long)]
        slow: Option<u64>,
        /// After COUNT, take nothing more (a reader that stopped) until terminated.
        #[arg(long)]
        then_stop: bool,
        /// Take events through a callback (`Service::subscribe_event_with`) instead of a
        /// mailbox; with SLOW, the callback itself sleeps (holding the link's receive task).
        #[arg(long, conflicts_with = "then_stop")]
        callback: bool,
    },
    /// Provide function ITEM: doubles its u64 argument after DELAY ms, or fails with FAIL.
    Provide {
        #[arg(long)]
        item: String,
        #[arg(long, default_value_t = 0)]
        delay_ms: u64,
        #[arg(long)]
        fail: Option<String>,
    },
    /// Call function NAME with ARG.
    Call {
        #[arg(long)]
        name: String,
        #[arg(long, default_value_t = 21)]
        arg: u64,
        #[arg(long, default_value_t = 2000)]
        timeout_ms: u64,
        /// Wait this long for a provider to be discovered first (0 = call at once).
        #[arg(long, default_value_t = 0)]
        wait_ms: u64,
        /// Within the same wait, first know a peer named NAME (`namespace/node`, or `node`
        /// without a namespace; once per peer: twice for two of one name), settled: its
        /// identity proof judged (where a roster is kept) and, when taken, its declarations
        /// in (so the call chooses among every provider there is).
        #[arg(long = "wait-peer", value_name = "NAME")]
        wait_peers: Vec<String>,
    },
    /// Accept files on ITEM into DIR.
    Sink {
        #[arg(long)]
        item: String,
        #[arg(long)]
        dir: PathBuf,
    },
    /// Send FILE to sink TO.
    Send {
        #[arg(long)]
        file: PathBuf,
        #[arg(long)]
        to: String,
        #[arg(long, default_value_t = 60)]
        retry_secs: u64,
    },
    /// Run the node only (a gateway when its network.xml makes it one) and print what it
    /// forwards whenever that changes.
    Gateway,
    /// The target of the hostile tests: provides function CALL (doubles its u64 argument),
    /// accepts files on SINK into DIR, subscribes to positions matching PATTERN, and prints a
    /// `report` line whenever what it delivered, executed, knows or refused changes.
    Victim {
        #[arg(long)]
        call: String,
        #[arg(long)]
        sink: String,
        #[arg(long)]
        dir: PathBuf,
        #[arg(long)]
        pattern: String,
    },
    /// List what the network offers after WAIT ms.
    List {
        #[arg(long, default_value_t = 1500)]
        wait_ms: u64,
    },
}

fn out(v: serde_json::Value) {
    use std::io::Write;
    let mut s = std::io::stdout().lock();
    let _ = writeln!(s, "{v}");
    let _ = s.flush();
}

fn config(args: &Args) -> anyhow::Result<NetworkConfig> {
    let mut c = base_config(args)?;
    if let Some(key_file) = &args.key_file {
        c.security = Some(marea::config::SecurityConfig {
            key_file: key_file.clone(),
            encrypt_radio: args.encrypt_radio,
            identity_file: args.identity_file.clone(),
            identities: args.identities.clone(),
        });
    }
    Ok(c)
}

fn base_config(args: &Args) -> anyhow::Result<NetworkConfig> {
    if let Some(path) = &args.config {
        return Ok(NetworkConfig::load(path)?);
    }
    let mut c = NetworkConfig::ethernet_loopback(&args.node);
    c.namespace = args.namespace.clone();
    c.domain = args.domain.clone();
    c.links = vec![LinkConfig::Ethernet(EthernetConfig {
        interface: std::net::Ipv4Addr::LOCALHOST,
        bind: "127.0.0.1:0".parse()?,
        multicast: std::net::SocketAddrV4::new(
            std::net::Ipv4Addr::new(239, 255, 77, 1),
            args.mcast_port,
        ),
        heartbeat: Duration::from_millis(args.heartbeat_ms),
        lease: Duration::from_millis(args.lease_ms),
        ..EthernetConfig::default()
    })];
    Ok(c)
}

/// `ev-pub --stream`: COUNT events through [`marea::EventStream`], each loss printed as
/// `{"lost": NODE, "events": N, "reason": ..}`, then `{"raised": COUNT, "lost_events": N}`
/// once every subscriber acknowledged every event or was lost.
async fn stream_events(ev: &marea::Event<u64>, count: u64, interval_ms: u64) -> anyhow::Result<()> {
    let started = Instant::now();
    let mut stream = ev.stream();
    let mut lost_events = 0u64;
    let mut report = |r: Result<(), marea::StreamError>| -> anyhow::Result<()> {
        match r {
            Ok(()) => Ok(()),
            Err(marea::StreamError::Lost {
                node, lost, reason, ..
            }) => {
                lost_events += lost;
                out(
                    json!({"lost": node, "events": lost, "reason": reason, "after_ms": started.elapsed().as_millis() as u64}),
                );
                Ok(())
            }
            Err(e) => Err(e.into()),
        }
    };
    for i in 0..count {
        report(stream.send(&i).await)?;
        if interval_ms > 0 {
            tokio::time::sleep(Duration::from_millis(interval_ms)).await;
        }
    }
    // A flush reports one lossy node at a time: again until none is left.
    loop {
        match stream.flush().await {
            Ok(()) => break,
            e => report(e)?,
        }
    }
    out(
        json!({"raised": count, "lost_events": lost_events, "elapsed_ms": started.elapsed().as_millis() as u64}),
    );
    Ok(())
}

#[tokio::main]
async fn main() -> anyhow::Result<()> {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_default_env()
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    let args = Args::parse();
    let cfg = config(&args)?;
    let node = Node::open(&cfg).await.context("opening the node")?;
    let svc = node.service(&args.service)?;
    let result = run(&node, &svc, &args).await;
    drop(svc);
    node.shutdown().await;
    result
}

async fn run(node: &Node, svc: &marea::Service, args: &Args) -> anyhow::Result<()> {
    match &args.cmd {
        Cmd::VarPub {
            item,
            count,
            interval_ms,
            usal_type,
        } => {
            type Set = Box<dyn Fn(&Position) -> Result<(), marea::PublishError>>;
            let (name, set): (String, Set) = if *usal_type {
                let v = svc.publish_variable::<usal_types::Position>(item)?;
                (
                    v.name().to_owned(),
                    Box::new(move |p: &Position| {
                        v.set(&usal_types::Position {
                            lat: p.lat,
                            lon: p.lon,
                            alt: p.alt,
                            heading: p.heading,
                            speed: p.speed,
                            alt_rel: p.alt,
                        })
                    }),
                )
            } else {
                let v = svc.publish_variable::<Position>(item)?;
                (v.name().to_owned(), Box::new(move |p: &Position| v.set(p)))
            };
            out(json!({"ready": name}));
            let mut longest = Duration::ZERO;
            for i in 0..*count {
                let t = Instant::now();
                let p = Position {
                    lat: 41.275 + i as f64 * 1e-6,
                    lon: 1.987,
                    alt: i as f64,
                    heading: 90.0,
                    speed: 1.5,
                };
                set(&p)?;
                longest = longest.max(t.elapsed());
                if *interval_ms > 0 {
                    tokio::time::sleep(Duration::from_millis(*interval_ms)).await;
                }
            }
            out(json!({"published": count, "longest_set_us": longest.as_micros() as u64}));
            marea::process::terminated().await;
        }
        Cmd::VarSub { pattern, count } => {
            let sub = svc.subscribe_variable::<Position>(pattern)?;
            out(json!({"ready": pattern}));
            let mut n = 0;
            loop {
                let s = tokio::select! {
                    _ = marea::process::terminated() => break,
                    s = sub.recv() => s,
                };
                match s {
                    Ok(s) => out(
                        json!({"name": s.name, "publisher": s.publisher, "seq": s.value.alt as u64}),
                    ),
                    Err(e) => out(json!({"error": e.to_string()})),
                }
                n += 1;
                if *count > 0 && n >= *count {
                    break;
                }
            }
        }
        Cmd::Health { pattern, count } => {
            let sub = svc.subscribe_variable::<marea::LinkHealth>(pattern)?;
            out(json!({"ready": pattern}));
            for _ in 0..*count {
                let s = tokio::select! {
                    _ = marea::process::terminated() => break,
                    s = sub.recv() => s,
                };
                match s {
                    Ok(s) => out(json!({
                        "name": s.name,
                        "publisher": s.publisher,
                        "link": s.value.link,
                        "peers": s.value.peers,
                        "in_bps": s.value.in_bps,
                        "out_bps": s.value.out_bps,
                        "auth_rejected": s.value.totals.auth_rejected,
                        "replay_rejected": s.value.totals.replay_rejected,
                        "corrupt": s.value.totals.corrupt,
                    })),
                    Err(e) => out(json!({"error": e.to_string()})),
                }
            }
        }
        Cmd::VarSubString { pattern } => {
            let sub = svc.subscribe_variable::<String>(pattern)?;
            out(json!({"ready": pattern}));
            tokio::select! {
                _ = marea::process::terminated() => {}
                s = sub.recv() => match s {
                    Ok(s) => out(json!({"value": s.value})),
                    Err(e) => out(json!({"error": e.to_string()})),
                }
            }
        }
        Cmd::EvPub {
            item,
            count,
            subs,
            window,
            interval_ms,
            stream,
        } => {
            let ev = svc.publish_event::<u64>(item)?;
            out(json!({"ready": ev.name()}));
            if !ev
                .wait_remote_subscribers(*subs, Duration::from_secs(30))
                .await
            {
                bail!("only {:?} subscribed within 30 s", ev.remote_subscribers());
            }
            out(json!({"subscribers": ev.remote_subscribers()}));
            out(json!({"peers": node.peers()}));
            if *stream {
                stream_events(&ev, *count, *interval_ms).await?;
                marea::process::terminated().await;
                return Ok(());
            }
            let mut inflight = std::collections::VecDeque::new();
            let mut reported = std::collections::HashSet::new();
            let mut acked_all = 0u64;
            let mut failed_raises = 0u64;
            let mut last_failed_ms = 0u64;
            let mut stalled = false;
            let started = Instant::now();
            let mut handle =
                |r: marea::RaiseReport, reported: &mut std::collections::HashSet<String>| {
                    if r.all_acknowledged() {
                        acked_all += 1;
                    } else {
                        failed_raises += 1;
                        last_failed_ms = started.elapsed().as_millis() as u64;
                    }
                    for (sub, reason) in r.failed() {
                        if reported.insert(sub.clone()) {
                            out(
                                json!({"failed": sub, "reason": reason, "after_ms": started.elapsed().as_millis() as u64}),
                            );
                        }
                    }
                };
            for i in 0..*count {
                inflight.push_back(ev.raise_nowait(&i)?);
                if inflight.len() >= *window {
                    if let Some(mut p) = inflight.pop_front() {
                        // A full window whose oldest event waits long is reported once (a test
                        // stops a subscriber and waits for this before killing it).
                        if !stalled {
                            match tokio::time::timeout(Duration::from_millis(300), &mut p).await {
                                Ok(r) => {
                                    handle(r, &mut reported);
                                    continue;
                                }
                                Err(_) => {
                                    stalled = true;
                                    out(
                                        json!({"stalled": inflight.len() + 1, "raised_so_far": i + 1}),
                                    );
                                }
                            }
                        }
                        handle(p.await, &mut reported);
                    }
                }
                if *interval_ms > 0 {
                    tokio::time::sleep(Duration::from_millis(*interval_ms)).await;
                }
            }
            while let Some(p) = inflight.pop_front() {
                handle(p.await, &mut reported);
            }
            out(
                json!({"raised": count, "acknowledged_by_all": acked_all, "failed_raises": failed_raises, "last_failed_ms": last_failed_ms, "elapsed_ms": started.elapsed().as_millis() as u64, "peers": node.peers()}),
            );
            marea::process::terminated().await;
        }
        Cmd::EvSub {
            pattern,
            count,
            from_any,
            slow,
            then_stop,
            callback,
        } => {
            if *callback {
                let (count, slow) = (*count, *slow);
                let check = std::sync::Mutex::new(InOrder::new(*from_any));
                let _sub = svc.subscribe_event_with::<u64, _>(pattern, move |s| {
                    let s = match s {
                        Ok(s) => s,
                        Err(e) => return out(json!({"error": e.to_string()})),
                    };
                    let mut c = check.lock().unwrap_or_else(|e| e.into_inner());
                    if c.n >= count {
                        return out(json!({"extra": s.value, "publisher": s.publisher}));
                    }
                    c.take(&s);
                    if c.n == count {
                        out(json!({"received": c.n, "in_order": c.in_order}));
                    }
                    if slow.is_some_and(|k| c.n % k.max(1) == 0) {
                        std::thread::sleep(Duration::from_millis(1));
                    }
                })?;
                out(json!({"ready": pattern, "pid": std::process::id()}));
                marea::process::terminated().await;
                return Ok(());
            }
            let sub = svc.subscribe_event::<u64>(pattern)?;
            out(json!({"ready": pattern, "pid": std::process::id()}));
            let mut check = InOrder::new(*from_any);
            let mut said_behind = false;
            while check.n < *count {
                let s = tokio::select! {
                    _ = marea::process::terminated() => break,
                    s = sub.recv() => s?,
                };
                check.take(&s);
                if slow.is_some_and(|k| check.n % k.max(1) == 0) {
                    let waiting = sub.pending();
                    if waiting > 16_384 && !said_behind {
                        said_behind = true;
                        out(json!({"behind": waiting}));
                    }
                    tokio::time::sleep(Duration::from_millis(1)).await;
                }
            }
            out(json!({"received": check.n, "in_order": check.in_order}));
            if *then_stop {
                marea::process::terminated().await;
                return Ok(());
            }
            // Stay until stopped so the publisher sees our acknowledgements and lease; anything
            // more that arrives is reported (a duplicate would show here).
            loop {
                let s = tokio::select! {
                    _ = marea::process::terminated() => break,
                    s = sub.recv() => s?,
                };
                out(json!({"extra": s.value, "publisher": s.publisher}));
            }
        }
        Cmd::Provide {
            item,
            delay_ms,
            fail,
        } => {
            let delay = Duration::from_millis(*delay_ms);
            let fail = fail.clone();
            let _f = svc.provide_function(item, move |x: u64| {
                let fail = fail.clone();
                async move {
                    // Tests wait for this line to know a call is in flight.
                    out(json!({"called": x}));
                    tokio::time::sleep(delay).await;
                    match fail {
                        Some(m) => Err(m),
                        None => Ok(x * 2),
                    }
                }
            })?;
            out(json!({"ready": svc.full_name(item)}));
            marea::process::terminated().await;
        }
        Cmd::Call {
            name,
            arg,
            timeout_ms,
            wait_ms,
            wait_peers,
        } => {
            let f = svc.function::<u64, u64>(name)?;
            if *wait_ms > 0 {
                let settled = |p: &marea::PeerInfo| match p.trust {
                    marea::PeerTrust::Pending => false,
                    marea::PeerTrust::Refused => true,
                    marea::PeerTrust::Claimed | marea::PeerTrust::Proven => p.declarations > 0,
                };
                let path =
                    |p: &marea::PeerInfo| marea::config::access::peer_path(&p.namespace, &p.name);
                node.wait_until(Duration::from_millis(*wait_ms), |n| {
                    let settled: Vec<String> =
                        n.peers().iter().filter(|p| settled(p)).map(path).collect();
                    let mut wanted = wait_peers.clone();
                    wanted.sort();
                    wanted.dedup();
                    wanted.iter().all(|w| {
                        let want = wait_peers.iter().filter(|x| *x == w).count();
                        settled.iter().filter(|s| *s == w).count() >= want
                    })
                })
                .await;
                f.wait_provider(Duration::from_millis(*wait_ms)).await;
            }
            let started = Instant::now();
            match f.call(arg, Duration::from_millis(*timeout_ms)).await {
                Ok(v) => out(json!({"ok": v, "ms": started.elapsed().as_millis() as u64})),
                Err(e) => {
                    let kind = e.kind();
                    out(
                        json!({"error": kind, "message": e.to_string(), "ms": started.elapsed().as_millis() as u64}),
                    );
                }
            }
        }
        Cmd::Sink { item, dir } => {
            let sink = svc.file_sink(item, dir)?;
            out(json!({"ready": sink.name()}));
            loop {
                let f = tokio::select! {
                    _ = marea::process::terminated() => break,
                    f = sink.recv() => f?,
                };
                out(
                    json!({"received": f.path, "size": f.size, "from": f.from, "resumed_from": f.resumed_from}),
                );
            }
        }
        Cmd::Send {
            file,
            to,
            retry_secs,
        } => {
            let t = svc.send_file(
                file,
                to,
                SendFileOptions {
                    retry_for: Duration::from_secs(*retry_secs),
                    ..Default::default()
                },
            );
            let mut watch = t.watch_progress();
            let progress = async move {
                let mut last_pct = u64::MAX;
                while watch.changed().await.is_ok() {
                    let p = *watch.borrow();
                    let pct = (p.acknowledged * 100).checked_div(p.total).unwrap_or(0);
                    if pct / 10 != last_pct / 10 {
                        last_pct = pct;
                        out(
                            json!({"progress": pct, "acknowledged": p.acknowledged, "sent": p.sent}),
                        );
                    }
                }
            };
            // The progress stream may end just before the result is ready: report progress
            // beside the transfer and stop reporting once it finished.
            let progress = tokio::spawn(progress);
            let r = t.wait().await;
            progress.abort();
            let r = match r {
                Ok(r) => r,
                Err(e) => {
                    let kind = match &e {
                        marea::FileSendError::Denied { .. } => "denied",
                        marea::FileSendError::Rejected { .. } => "rejected",
                        _ => "failed",
                    };
                    out(json!({"error": kind, "message": e.to_string()}));
                    return Err(e.into());
                }
            };
            out(
                json!({"done": r.size, "sent": r.sent, "resumed_from": r.resumed_from, "attempts": r.attempts, "ms": r.elapsed.as_millis() as u64}),
            );
        }
        Cmd::Gateway => {
            out(json!({"ready": node.name(), "gateway": node.is_gateway()}));
            let mut shown = serde_json::Value::Null;
            let mut tick = tokio::time::interval(Duration::from_millis(100));
            loop {
                tokio::select! {
                    _ = marea::process::terminated() => break,
                    _ = tick.tick() => {}
                }
                let items: Vec<serde_json::Value> = node
                    .forwarded()
                    .into_iter()
                    .map(|f| json!({"name": f.name, "kind": f.kind.as_str(), "origin": f.origin, "cached": f.cached}))
                    .collect();
                let now = serde_json::Value::from(items);
                if now != shown {
                    out(json!({"forwarded": now}));
                    shown = now;
                }
            }
        }
        Cmd::Victim {
            call,
            sink,
            dir,
            pattern,
        } => victim(node, svc, call, sink, dir, pattern).await?,
        Cmd::List { wait_ms } => {
            tokio::time::sleep(Duration::from_millis(*wait_ms)).await;
            out(serde_json::to_value(node.catalog())?);
        }
    }
    Ok(())
}

/// Variables a victim publishes (`status0`..), once a second.
const VICTIM_VARIABLES: usize = 8;

/// What a victim delivered and executed, for [`Cmd::Victim`]'s reports.
#[derive(Default)]
struct Delivered {
    /// Calls executed, by argument.
    called: Vec<u64>,
    /// Samples delivered, by "publisher name".
    samples: std::collections::BTreeMap<String, u64>,
    /// Files stored: (sender, size).
    files: Vec<(String, u64)>,
    /// Samples carrying the hostile tests' marker (latitude [`FORGED_LAT`]), whoever sent them.
    marked: u64,
}

/// The latitude of the positions the hostile tests forge: no genuine publisher sends it.
const FORGED_LAT: f64 = 666.0;

async fn victim(
    node: &Node,
    svc: &marea::Service,
    call: &str,
    sink: &str,
    dir: &std::path::Path,
    pattern: &str,
) -> anyhow::Result<()> {
    use std::sync::{Arc, Mutex};
    let delivered = Arc::new(Mutex::new(Delivered::default()));
    let d = delivered.clone();
    let _f = svc.provide_function(call, move |x: u64| {
        let d = d.clone();
        async move {
            if let Ok(mut d) = d.lock() {
                d.called.push(x);
            }
            Ok::<u64, String>(x.wrapping_mul(2))
        }
    })?;
    let files = svc.file_sink(sink, dir)?;
    let positions = svc.subscribe_variable::<Position>(pattern)?;
    // What a vehicle's service publishes, as routes an attacker's interests can match.
    let status: Vec<marea::Variable<u64>> = (0..VICTIM_VARIABLES)
        .map(|k| svc.publish_variable(&format!("status{k}")))
        .collect::<Result<_, _>>()?;
    let mut published = tokio::time::interval(Duration::from_secs(1));
    out(json!({"ready": svc.full_name(call), "addrs": node.link_addrs()}));
    let mut tick = tokio::time::interval(Duration::from_millis(50));
    let mut shown = serde_json::Value::Null;
    loop {
        tokio::select! {
            _ = marea::process::terminated() => break,
            _ = tick.tick() => {}
            _ = published.tick() => {
                for (k, v) in status.iter().enumerate() {
                    v.set(&(k as u64))?;
                }
                continue;
            }
            s = positions.recv() => {
                if let (Ok(s), Ok(mut d)) = (s, delivered.lock()) {
                    *d.samples.entry(format!("{} {}", s.publisher, s.name)).or_default() += 1;
                    if s.value.lat == FORGED_LAT {
                        d.marked += 1;
                    }
                }
                continue;
            }
            f = files.recv() => {
                let f = f?;
                if let Ok(mut d) = delivered.lock() {
                    d.files.push((f.from, f.size));
                }
            }
        }
        let report = {
            let d = delivered
                .lock()
                .map_err(|_| anyhow::anyhow!("report lock poisoned"))?;
            let r = node.refusals();
            // By name (a flood of invented peers may share one): how many, and an address.
            let mut peers = std::collections::BTreeMap::<String, u64>::new();
            let mut peer_addrs = std::collections::BTreeMap::<String, String>::new();
            let mut authenticated = Vec::new();
            let mut pair_sealed = Vec::new();
            let mut declarations = 0;
            for p in node.peers() {
                declarations += p.declarations;
                if p.authenticated_namespaces
                    .as_ref()
                    .is_some_and(|n| !n.is_empty())
                {
                    authenticated.push(format!("{}/{}", p.namespace, p.name));
                }
                if p.pair_sealed {
                    pair_sealed.push(format!("{}/{}", p.namespace, p.name));
                }
                *peers
                    .entry(format!("{}/{}", p.namespace, p.name))
                    .or_default() += 1;
                peer_addrs.insert(format!("{}/{}", p.namespace, p.name), p.addr);
            }
            json!({
                "called": d.called,
                "marked": d.marked,
                "samples": d.samples,
                "files": d.files,
                "peers": peers,
                "peer_addrs": peer_addrs,
                "authenticated": authenticated,
                "pair_sealed": pair_sealed,
                "declarations": declarations,
                "frames_in": node.link_stats().iter().map(|(_, s)| s.frames_in).sum::<u64>(),
                "refusals": {
                    "denied": r.denied, "rejected": r.rejected,
                    "auth_rejected": r.auth_rejected, "replay_rejected": r.replay_rejected,
                    "undecodable": r.undecodable, "unknown_sender": r.unknown_sender,
                    "bad_declarations": r.bad_declarations, "peers_refused": r.peers_refused,
                    "peers_evicted": r.peers_evicted, "total": r.total(),
                },
            })
        };
        // Sample counts change 50 times a second: report at the tick, whatever changed.
        if report != shown {
            out(json!({"report": report}));
            shown = report;
        }
    }
    Ok(())
}

/// `ev-sub`'s check of each publisher's sequence numbers (printing the first value and every
/// one out of order).
struct InOrder {
    next: std::collections::HashMap<marea::SharedStr, u64>,
    /// Events taken.
    n: u64,
    in_order: bool,
    /// Any first sequence number is accepted per publisher.
    from_any: bool,
}

impl InOrder {
    fn new(from_any: bool) -> Self {
        InOrder {
            next: Default::default(),
            n: 0,
            in_order: true,
            from_any,
        }
    }

    fn take(&mut self, s: &marea::Sample<u64>) {
        let first = if self.from_any { s.value } else { 0 };
        if self.n == 0 {
            out(json!({"first": s.value}));
        }
        let expected = self.next.entry(s.publisher.clone()).or_insert(first);
        if s.value != *expected {
            self.in_order = false;
            out(json!({"out_of_order": s.value, "expected": *expected}));
        }
        *expected = s.value + 1;
        self.n += 1;
    }
}
