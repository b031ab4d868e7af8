//! `cargo bench --bench shm`: the shared-memory link's figures as JSON lines
//! `{"metric": ..., "value": ..., "unit": ...}`, with a raw iceoryx2 publish-subscribe
//! ping-pong measured in the same run as the baseline. The baseline waits the way the link
//! waits: by default an iceoryx2 event per message, the receiver sleeping on its listener
//! (`shm.var64.*` against `shm.raw_iceoryx2_64.*`); with `wait="spin"` nobody notifies and the
//! receiver busy-polls its subscriber (`shm.var64.spin.*` against
//! `shm.raw_iceoryx2_64.spin.*`).

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use iceoryx2::prelude::*;
use marea::config::{LinkConfig, ShmConfig, ShmWait};
use marea::{NetworkConfig, Node, SendFileOptions, Service};

type Payload64 = [u64; 8];
type Ipc = ipc_threadsafe::Service;

fn metric(name: &str, value: f64, unit: &str) {
    println!(
        "{}",
        serde_json::json!({"metric": name, "value": value, "unit": unit})
    );
}

fn cfg(node: &str, service: &str, wait: ShmWait) -> NetworkConfig {
    let mut c = NetworkConfig::ethernet_loopback(node);
    c.domain = format!("bench-{}-{}", std::process::id(), wait.as_str());
    c.links = vec![LinkConfig::Shm(ShmConfig {
        service: service.into(),
        wait,
        ..ShmConfig::default()
    })];
    c
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// One side of the raw ping-pong: a subscriber and listener on `rx`, a publisher and notifier
/// on `tx`. The initiator sends first and times each round trip.
fn raw_side(
    prefix: &str,
    (rx, tx): (&str, &str),
    n: usize,
    initiator: bool,
    wait: ShmWait,
) -> Result<Vec<f64>, BoxError> {
    let node = NodeBuilder::new()
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<Ipc>()?;
    let pubsub = |name: &str| {
        node.service_builder(&ServiceName::new(&format!("{prefix}/{name}"))?)
            .publish_subscribe::<[u8]>()
            .subscriber_max_buffer_size(16)
            .max_publishers(2)
            .max_subscribers(2)
            .open_or_create()
            .map_err(|e| -> BoxError { format!("{e:?}").into() })
    };
    let event = |name: &str| {
        node.service_builder(&ServiceName::new(&format!("{prefix}/{name}/wake"))?)
            .event()
            .open_or_create()
            .map_err(|e| -> BoxError { format!("{e:?}").into() })
    };
    let (rs, ts, re, te) = (pubsub(rx)?, pubsub(tx)?, event(rx)?, event(tx)?);
    let sub = rs.subscriber_builder().create()?;
    let publisher = ts.publisher_builder().initial_max_slice_len(64).create()?;
    let listener = re.listener_builder().create()?;
    let notifier = te.notifier_builder().create()?;
    // Both sides connected before the first message.
    while ts.dynamic_config().number_of_subscribers() < 1 {
        std::thread::sleep(Duration::from_millis(1));
    }
    let msg = [7u8; 64];
    let mut out = Vec::with_capacity(n);
    let spin = wait == ShmWait::Spin;
    let send = || -> Result<(), BoxError> {
        let s = publisher.loan_slice_uninit(64)?.write_from_slice(&msg);
        s.send()?;
        if !spin {
            notifier.notify()?;
        }
        Ok(())
    };
    for _ in 0..n {
        let t = Instant::now();
        if initiator {
            send()?;
        }
        let give_up = t + Duration::from_secs(5);
        loop {
            if sub.receive()?.is_some() {
                break;
            }
            if spin {
                if Instant::now() > give_up {
                    return Err("no answer within 5 s".into());
                }
                std::hint::spin_loop();
            } else {
                listener.timed_wait(|_| {}, Duration::from_secs(5))?;
            }
        }
        if !initiator {
            send()?;
        }
        out.push(t.elapsed().as_secs_f64() * 1e6);
    }
    Ok(out)
}

fn raw_ping_pong(n: usize, wait: ShmWait) -> Result<Vec<f64>, BoxError> {
    let prefix = format!("bench-raw-{}-{}", std::process::id(), wait.as_str());
    let p2 = prefix.clone();
    let echo = std::thread::spawn(move || raw_side(&p2, ("ping", "pong"), n, false, wait));
    let mut rtts = raw_side(&prefix, ("pong", "ping"), n, true, wait)?;
    echo.join().map_err(|_| "echo thread panicked")??;
    rtts.sort_by(f64::total_cmp);
    Ok(rtts)
}

fn rss_kb(pid: u32) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    let line = status.lines().find(|l| l.starts_with("VmRSS:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

/// Variable round trips: `sa` publishes ping, `sb` answers pong with the same value; `n` timed
/// after 1000 to warm up. Sorted, in microseconds.
/// The figures of one round-trip pair: `<var><mode>.rtt_p50_us`/`_p99_us`, the same for the raw
/// baseline, and `<var><mode>.rtt_ratio_to_raw` (p50), from sorted samples.
fn rtt_pair(var: &str, raw_name: &str, mode: &str, var_rtts: &[f64], raw_rtts: &[f64]) {
    for (name, rtts) in [(var, var_rtts), (raw_name, raw_rtts)] {
        metric(
            &format!("{name}{mode}.rtt_p50_us"),
            percentile(rtts, 0.5),
            "us",
        );
        metric(
            &format!("{name}{mode}.rtt_p99_us"),
            percentile(rtts, 0.99),
            "us",
        );
    }
    metric(
        &format!("{var}{mode}.rtt_ratio_to_raw"),
        percentile(var_rtts, 0.5) / percentile(raw_rtts, 0.5),
        "ratio",
    );
}

async fn var_rtts(sa: &Service, sb: &Service, n: usize) -> Result<Vec<f64>, BoxError> {
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
    Ok(rtts)
}

#[tokio::main]
async fn main() -> Result<(), BoxError> {
    let n = 20_000;
    // Busy-polling first, on nodes of their own that are closed before anything else runs (two
    // spinning receive threads would take the cores from the rest).
    let spin_rtts = {
        let service = format!("bench{}spin", std::process::id());
        let c = Node::open(&cfg("bench-c", &service, ShmWait::Spin)).await?;
        let d = Node::open(&cfg("bench-d", &service, ShmWait::Spin)).await?;
        let (sc, sd) = (c.service("a")?, d.service("b")?);
        // The pinging side is a task too, as a subscriber of a busy-polled link would be: its
        // worker then never parks, so a wake-up is a queue push rather than a thread switch.
        let rtts = tokio::spawn(async move {
            let r = var_rtts(&sc, &sd, n).await.map_err(|e| e.to_string());
            drop((sc, sd));
            r
        })
        .await??;
        c.shutdown().await;
        d.shutdown().await;
        rtts
    };
    let raw_spin = tokio::task::spawn_blocking(move || raw_ping_pong(n, ShmWait::Spin)).await??;

    let service = format!("bench{}", std::process::id());
    let a = Node::open(&cfg("bench-a", &service, ShmWait::Event)).await?;
    let b = Node::open(&cfg("bench-b", &service, ShmWait::Event)).await?;
    let sa = a.service("a")?;
    let sb = b.service("b")?;
    let rtts = var_rtts(&sa, &sb, n).await?;
    let raw = tokio::task::spawn_blocking(move || raw_ping_pong(n, ShmWait::Event)).await??;
    rtt_pair("shm.var64", "shm.raw_iceoryx2_64", "", &rtts, &raw);
    rtt_pair(
        "shm.var64",
        "shm.raw_iceoryx2_64",
        ".spin",
        &spin_rtts,
        &raw_spin,
    );

    // Variable throughput: 100 telemetry variables published round robin.
    let vars: Vec<_> = (0..100)
        .map(|i| sa.publish_variable::<Payload64>(&format!("tm/v{i}")))
        .collect::<Result<_, _>>()?;
    let sub = sb.subscribe_variable::<Payload64>("a/tm/*")?;
    for v in &vars {
        v.wait_remote_subscribers(1, Duration::from_secs(10)).await;
    }
    let received = Arc::new(AtomicU64::new(0));
    let r = received.clone();
    let counter = tokio::spawn(async move {
        while sub.recv().await.is_ok() {
            r.fetch_add(1, Ordering::Relaxed);
        }
    });
    let secs = 3.0;
    let start = Instant::now();
    let begin = received.load(Ordering::Relaxed);
    let mut i = 0u64;
    while start.elapsed().as_secs_f64() < secs {
        for _ in 0..64 {
            vars[(i % 100) as usize].set(&[i; 8])?;
            i += 1;
        }
        tokio::task::yield_now().await;
    }
    tokio::time::sleep(Duration::from_millis(100)).await;
    let var_rate =
        (received.load(Ordering::Relaxed) - begin) as f64 / start.elapsed().as_secs_f64();
    counter.abort();
    metric("shm.var64.sets_per_s", i as f64 / secs, "msgs/s");
    metric("shm.var64.msgs_per_s", var_rate, "msgs/s");

    // Reliable events with a window in flight, counted at the subscriber.
    let ev = sa.publish_event::<Payload64>("ev")?;
    let evsub = sb.subscribe_event::<Payload64>("a/ev")?;
    ev.wait_remote_subscribers(1, Duration::from_secs(10)).await;
    let total = 200_000u64;
    let start = Instant::now();
    let recv = tokio::spawn(async move {
        let mut n = 0u64;
        while n < total && evsub.recv().await.is_ok() {
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
        "shm.event64.msgs_per_s",
        got as f64 / start.elapsed().as_secs_f64(),
        "msgs/s",
    );

    // File transfer.
    let dir = tempfile::tempdir()?;
    let path = dir.path().join("f64mb.bin");
    let data: Vec<u8> = (0..(64u32 << 20))
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
        "shm.file_64mb.mb_per_s",
        report.size as f64 / 1e6 / secs,
        "MB/s",
    );
    drop((vars, ev, sink));
    drop((sa, sb));
    a.shutdown().await;
    b.shutdown().await;

    // Resident memory of an idle node (a marea-probe process on shm only, one peer).
    let xml = dir.path().join("idle.xml");
    std::fs::write(
        &xml,
        format!(
            "<network node=\"idle\" domain=\"bench-idle-{0}\"><shm service=\"idle{0}\"/></network>",
            std::process::id()
        ),
    )?;
    let probe = env!("CARGO_BIN_EXE_marea-probe");
    let spawn = |item: &str| {
        std::process::Command::new(probe)
            .args([
                "--config",
                xml.to_str().unwrap_or_default(),
                "provide",
                "--item",
                item,
            ])
            .stdout(std::process::Stdio::null())
            .spawn()
    };
    let mut idle = spawn("f")?;
    let mut peer = spawn("g")?;
    tokio::time::sleep(Duration::from_secs(3)).await;
    let rss = rss_kb(idle.id());
    let _ = idle.kill();
    let _ = peer.kill();
    let _ = idle.wait();
    let _ = peer.wait();
    if let Some(kb) = rss {
        metric("shm.idle_node_rss_kb", kb as f64, "kB");
    }
    Ok(())
}
