//! Zenoh 1.x in peer mode over TCP on loopback: the responder (`pong`, `sub`, the first `idle`)
//! listens, the initiator connects; multicast scouting is off so only the two talk. Reliable
//! with `CongestionControl::Block` (a full queue holds the publisher up, nothing is dropped);
//! everything else is Zenoh's default, as a user would have it; under load (`ping-load`) the
//! pings and pongs go at `Priority::RealTime` and express, the bulk stream at
//! `Priority::DataLow`, as a user would ask commands to pass a video. KEY is `PORT:NAME`; in a
//! fan-out every subscriber listens on its own port and the publisher's KEY lists them all,
//! `PORT,PORT,...:NAME`. With a router (`router`, then the `-client` roles): the router
//! listens on PORT and the others are clients of it; each subscriber declares a liveliness
//! token, so the publisher starts once every one is known.

use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::{anyhow, Context};
use peers_common::{
    finish_sub, payload, ready, seq, subscribers, timed_round_trips, under_load, Args, Arrivals,
    BulkMeter, Control, BULK_FRAME,
};
use zenoh::qos::{CongestionControl, Priority};

fn main() -> anyhow::Result<()> {
    let args = Args::parse()?;
    let control = Control::start(true);
    let rt = tokio::runtime::Runtime::new().context("tokio runtime")?;
    rt.block_on(run(args, control))
}

async fn session(ports: &str, listen: bool, mode: &str) -> anyhow::Result<zenoh::Session> {
    let mut c = zenoh::Config::default();
    let set = |c: &mut zenoh::Config, k: &str, v: &str| {
        c.insert_json5(k, v)
            .map_err(|e| anyhow!("zenoh config {k}={v}: {e}"))
    };
    set(&mut c, "mode", &format!("{mode:?}"))?;
    set(&mut c, "scouting/multicast/enabled", "false")?;
    let ep = format!(
        "[{}]",
        ports
            .split(',')
            .map(|p| format!(r#""tcp/127.0.0.1:{p}""#))
            .collect::<Vec<_>>()
            .join(",")
    );
    if listen {
        set(&mut c, "listen/endpoints", &ep)?;
    } else {
        set(&mut c, "listen/endpoints", "[]")?;
        set(&mut c, "connect/endpoints", &ep)?;
    }
    zenoh::open(c).await.map_err(|e| anyhow!("zenoh open: {e}"))
}

async fn publisher(
    s: &zenoh::Session,
    key: String,
) -> anyhow::Result<zenoh::pubsub::Publisher<'static>> {
    publisher_at(s, key, Priority::default(), false).await
}

/// A reliable publisher at `priority`, `express` (sent at once, not batched) or not.
async fn publisher_at(
    s: &zenoh::Session,
    key: String,
    priority: Priority,
    express: bool,
) -> anyhow::Result<zenoh::pubsub::Publisher<'static>> {
    let p = s
        .declare_publisher(key.clone())
        .congestion_control(CongestionControl::Block)
        .priority(priority)
        .express(express)
        .await
        .map_err(|e| anyhow!("declare publisher {key}: {e}"))?;
    Ok(p)
}

/// Waits until the publisher has a subscriber (the other process), and is connected to every
/// subscriber of a fan-out.
async fn matched(s: &zenoh::Session, p: &zenoh::pubsub::Publisher<'_>) -> anyhow::Result<()> {
    let end = Instant::now() + Duration::from_secs(15);
    let n = subscribers();
    loop {
        let m = p
            .matching_status()
            .await
            .map_err(|e| anyhow!("matching status: {e}"))?;
        if m.matching() && (n == 1 || s.info().peers_zid().await.count() >= n) {
            return Ok(());
        }
        if Instant::now() > end {
            anyhow::bail!("no zenoh subscriber matched within 15 s");
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    }
}

/// Waits until every subscriber of the run (behind the router) declared its liveliness token.
async fn all_alive(s: &zenoh::Session, name: &str) -> anyhow::Result<()> {
    let end = Instant::now() + Duration::from_secs(15);
    let n = subscribers();
    loop {
        let replies = s
            .liveliness()
            .get(format!("{name}/alive/*"))
            .await
            .map_err(|e| anyhow!("liveliness get: {e}"))?;
        let mut alive = 0;
        while let Ok(r) = replies.recv_async().await {
            alive += usize::from(r.result().is_ok());
        }
        if alive >= n {
            return Ok(());
        }
        if Instant::now() > end {
            anyhow::bail!("{alive} of {n} zenoh subscribers known within 15 s");
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Puts `size`-byte messages on `p` for `secs`; prints `result SENT SECS`.
async fn publish_for(
    p: &zenoh::pubsub::Publisher<'_>,
    size: usize,
    secs: f64,
) -> anyhow::Result<()> {
    let msg = payload(size, 0);
    let start = Instant::now();
    let mut sent = 0u64;
    while start.elapsed().as_secs_f64() < secs {
        for _ in 0..64 {
            p.put(msg.clone()).await.map_err(|e| anyhow!("put: {e}"))?;
            sent += 1;
        }
    }
    println!("result {sent} {}", start.elapsed().as_secs_f64());
    Ok(())
}

/// One ping of `size` bytes numbered `i`, until its pong comes back; when it started.
async fn round_trip(
    p: &zenoh::pubsub::Publisher<'_>,
    sub: &zenoh::pubsub::Subscriber<zenoh::handlers::FifoChannelHandler<zenoh::sample::Sample>>,
    size: usize,
    i: u64,
) -> anyhow::Result<Instant> {
    let t = Instant::now();
    p.put(payload(size, i))
        .await
        .map_err(|e| anyhow!("ping put: {e}"))?;
    loop {
        let sample = tokio::time::timeout(Duration::from_secs(5), sub.recv_async())
            .await
            .context("no pong within 5 s")?
            .map_err(|e| anyhow!("ping recv: {e}"))?;
        if seq(&sample.payload().to_bytes()) == Some(i) {
            return Ok(t);
        }
    }
}

async fn run(args: Args, control: Arc<Control>) -> anyhow::Result<()> {
    let (port, name) = args
        .key
        .split_once(':')
        .ok_or_else(|| anyhow!("KEY {:?}: expected PORT:NAME", args.key))?;
    let listen = matches!(args.role.as_str(), "pong" | "pong-load" | "sub" | "idle" | "router")
        && !name.ends_with("/partner");
    let mode = match args.role.as_str() {
        "router" => "router",
        r if r.ends_with("-client") => "client",
        _ => "peer",
    };
    let s = session(port, listen, mode).await?;
    match args.role.as_str() {
        "router" => {
            ready("");
            while !control.closed() {
                tokio::time::sleep(Duration::from_millis(50)).await;
            }
            Ok(())
        }
        "pub-client" => {
            let p = publisher(&s, format!("{name}/data")).await?;
            all_alive(&s, name).await?;
            ready("");
            publish_for(&p, args.size, args.param).await
        }
        "pong" | "pong-load" => {
            // Under load it also takes the bulk stream, and answers at the pings' priority.
            let load = args.role == "pong-load";
            let sub = s
                .declare_subscriber(format!("{name}/ping"))
                .await
                .map_err(|e| anyhow!("declare subscriber: {e}"))?;
            let _bulk = match load {
                true => Some(
                    s.declare_subscriber(format!("{name}/bulk"))
                        .callback(|_sample| {})
                        .await
                        .map_err(|e| anyhow!("declare subscriber: {e}"))?,
                ),
                false => None,
            };
            let key = format!("{name}/pong");
            let p = match load {
                true => publisher_at(&s, key, Priority::RealTime, true).await?,
                false => publisher(&s, key).await?,
            };
            ready("");
            while let Ok(sample) = sub.recv_async().await {
                let bytes = sample.payload().to_bytes().into_owned();
                p.put(bytes).await.map_err(|e| anyhow!("pong put: {e}"))?;
            }
            Ok(())
        }
        "ping" => {
            let sub = s
                .declare_subscriber(format!("{name}/pong"))
                .await
                .map_err(|e| anyhow!("declare subscriber: {e}"))?;
            let p = publisher(&s, format!("{name}/ping")).await?;
            matched(&s, &p).await?;
            ready("");
            let mut one = |i| round_trip(&p, &sub, args.size, i);
            timed_round_trips(args.param as usize, 0, &mut one)
                .await?
                .finish();
            Ok(())
        }
        "ping-load" => {
            let sub = s
                .declare_subscriber(format!("{name}/pong"))
                .await
                .map_err(|e| anyhow!("declare subscriber: {e}"))?;
            let p = publisher_at(&s, format!("{name}/ping"), Priority::RealTime, true).await?;
            let bulk = publisher_at(&s, format!("{name}/bulk"), Priority::DataLow, false).await?;
            matched(&s, &p).await?;
            matched(&s, &bulk).await?;
            ready("");
            let mut one = |i| round_trip(&p, &sub, args.size, i);
            let idle = timed_round_trips(args.param as usize, 0, &mut one)
                .await?
                .percentiles();
            let meter = Arc::new(BulkMeter::default());
            let m = meter.clone();
            let streamer = tokio::spawn(async move {
                let frame = payload(BULK_FRAME, 0);
                while !m.stopped() {
                    bulk.put(frame.clone())
                        .await
                        .map_err(|e| anyhow!("bulk put: {e}"))?;
                    m.add(frame.len());
                }
                Ok::<_, anyhow::Error>(())
            });
            under_load(args.param as usize, idle, &meter, streamer, one).await
        }
        "sub" | "sub-client" => {
            let arrivals = Arc::new(Arrivals::default());
            let a = arrivals.clone();
            let _sub = s
                .declare_subscriber(format!("{name}/data"))
                .callback(move |_sample| a.add())
                .await
                .map_err(|e| anyhow!("declare subscriber: {e}"))?;
            // Behind a router the publisher counts its subscribers by their tokens.
            let _alive = match args.role.as_str() {
                "sub-client" => Some(
                    s.liveliness()
                        .declare_token(format!("{name}/alive/{}", std::process::id()))
                        .await
                        .map_err(|e| anyhow!("liveliness token: {e}"))?,
                ),
                _ => None,
            };
            ready("");
            tokio::task::spawn_blocking(move || finish_sub(&arrivals, &control)).await?;
            Ok(())
        }
        "pub" => {
            let p = publisher(&s, format!("{name}/data")).await?;
            matched(&s, &p).await?;
            ready("");
            publish_for(&p, args.size, args.param).await
        }
        "idle" => {
            ready("");
            std::future::pending().await
        }
        other => anyhow::bail!("unknown role {other:?}"),
    }
}
