//! Link authentication figures (`auth.*`): the bytes a sealed position sample takes on UDP and
//! on serial (built by the links' own framing code), and the round trip and rate of 64-byte
//! variables over UDP sealed as a `usal run` mission seals them (the domain key, an identity
//! per node and the roster, so every frame between the two nodes is sealed with their pair's
//! keys) against the same without a key, measured in the same run, interleaved round by
//! round; each ratio is the median of the rounds' ratios, so machine noise hits both sides
//! alike.

use std::time::{Duration, Instant};

use marea::codec::{encode_message, encode_payload};
use marea::config::{EthernetConfig, LinkConfig, SecurityConfig};
use marea::link::auth::{DomainKey, LinkSecurity, Profile, Sealer};
use marea::link::datagram::{self, DatagramWriter};
use marea::link::serial::stp::{Stp, StpConfig};
use marea::protocol::Message;
use marea::{NetworkConfig, Node};

use super::metric::metric;

type Payload64 = [u64; 8];

/// Rounds (each measures both modes).
const ROUNDS: usize = 8;
/// Round trips per round.
const RTTS: usize = 3000;
/// Publishing time per rate round.
const RATE_SECS: f64 = 0.5;

fn position_message() -> Vec<u8> {
    let payload = encode_payload(&(41.0f64, 1.9f64, 30.0f64, 90.0f32, 1.5f32))
        .expect("a plain tuple encodes");
    encode_message(&Message::Var { id: 3, payload })
}

/// The sealed datagram the UDP link sends for one lone position sample.
fn udp_bytes(key: &DomainKey) -> usize {
    let mut w = DatagramWriter::new(1400);
    w.push_fast(&position_message());
    let mut d = w.take();
    d[0] = datagram::sealed_kind(d[0]);
    Sealer::new(key, Profile::UDP).seal(&mut d, usize::MAX);
    d.len()
}

/// The bytes the serial engine writes for one lone position sample (mean over many frames:
/// a seal byte equal to DLE is doubled on the line).
fn serial_bytes(key: &DomainKey) -> f64 {
    let sec = LinkSecurity {
        key: key.clone(),
        encrypt_radio: false,
    };
    let cfg = StpConfig::new(57_600, Duration::from_millis(1500), 300, 20);
    let mut stp: Stp<()> = Stp::new(cfg, 1).secured(Some(&sec));
    let msg = position_message();
    let mut now = Instant::now();
    let (mut total, mut frames) = (0usize, 0usize);
    for _ in 0..1000 {
        stp.push_fast(now, Some(1), msg.clone());
        while let Some(wire) = stp.poll_transmit(now) {
            total += wire.len();
            frames += 1;
        }
        // Let the paced line drain before the next sample.
        now += Duration::from_millis(100);
    }
    total as f64 / frames.max(1) as f64
}

fn config(node: &str, domain: &str, port: u16, security: Option<SecurityConfig>) -> NetworkConfig {
    let mut c = NetworkConfig::ethernet_loopback(node);
    c.domain = domain.into();
    c.links = vec![LinkConfig::Ethernet(EthernetConfig {
        interface: std::net::Ipv4Addr::LOCALHOST,
        bind: "127.0.0.1:0".parse().expect("literal address"),
        multicast: std::net::SocketAddrV4::new(std::net::Ipv4Addr::new(239, 255, 77, 9), port),
        ..EthernetConfig::default()
    })];
    c.security = security;
    c
}

/// The seal of node `node` (identity `<dir>/<node>.id`), as a mission's: the domain key, its
/// identity, the roster.
fn sealed(dir: &std::path::Path, node: &str) -> SecurityConfig {
    SecurityConfig {
        key_file: dir.join("domain.key"),
        encrypt_radio: false,
        identity_file: Some(dir.join(format!("{node}.id"))),
        identities: Some(dir.join("identities.xml")),
    }
}

/// Two nodes measuring round trips (ping/pong) and rate (100 variables into a subscriber).
struct Pair {
    a: Node,
    b: Node,
    ping: marea::Variable<Payload64>,
    pongs: marea::Subscription<Payload64>,
    echo: tokio::task::JoinHandle<()>,
    vars: Vec<marea::Variable<Payload64>>,
    sink: std::sync::Arc<marea::Subscription<Payload64>>,
}

impl Pair {
    async fn open(tag: &str, port: u16, seal: Option<&std::path::Path>) -> Pair {
        let domain = format!("bench-auth-{tag}-{}", std::process::id());
        let a = Node::open(&config("a", &domain, port, seal.map(|d| sealed(d, "a"))))
            .await
            .expect("node a");
        let b = Node::open(&config("b", &domain, port, seal.map(|d| sealed(d, "b"))))
            .await
            .expect("node b");
        if seal.is_some() {
            let paired = |n: &Node| n.peers().iter().any(|p| p.pair_sealed);
            let both = a.wait_until(Duration::from_secs(10), paired).await
                && b.wait_until(Duration::from_secs(10), paired).await;
            assert!(both, "the keyed nodes never sealed with their pair's keys");
        }
        let sa = a.service("a").expect("service");
        let sb = b.service("b").expect("service");
        let ping = sa.publish_variable::<Payload64>("ping").expect("ping");
        let pongs = sa.subscribe_variable::<Payload64>("b/pong").expect("pongs");
        let pong = sb.publish_variable::<Payload64>("pong").expect("pong");
        let pings = sb.subscribe_variable::<Payload64>("a/ping").expect("pings");
        let vars: Vec<_> = (0..100)
            .map(|i| sa.publish_variable::<Payload64>(&format!("tm/v{i}")))
            .collect::<Result<_, _>>()
            .expect("variables");
        let sink = std::sync::Arc::new(sb.subscribe_variable::<Payload64>("a/tm/*").expect("sink"));
        ping.wait_remote_subscribers(1, Duration::from_secs(10))
            .await;
        pong.wait_remote_subscribers(1, Duration::from_secs(10))
            .await;
        for v in &vars {
            v.wait_remote_subscribers(1, Duration::from_secs(10)).await;
        }
        let echo = tokio::spawn(async move {
            while let Ok(s) = pings.recv().await {
                if pong.set(&s.value).is_err() {
                    break;
                }
            }
        });
        Pair {
            a,
            b,
            ping,
            pongs,
            echo,
            vars,
            sink,
        }
    }

    /// Median round trip in µs over `n` pings.
    async fn rtt_p50(&self, n: usize, base: u64) -> f64 {
        let mut rtts = Vec::with_capacity(n);
        for i in 0..n as u64 {
            let v: Payload64 = [base + i; 8];
            let t = Instant::now();
            self.ping.set(&v).expect("set");
            loop {
                let s = self.pongs.recv().await.expect("pong");
                if s.value == v {
                    break;
                }
            }
            rtts.push(t.elapsed().as_secs_f64() * 1e6);
        }
        rtts.sort_by(f64::total_cmp);
        rtts[rtts.len() / 2]
    }

    /// Values received per second while 100 variables are set round robin for `secs`.
    async fn rate(&self, secs: f64) -> f64 {
        // The subscriber counts in a task of its own (another worker), as a receiving
        // service would, not only when the publisher yields.
        let sink = self.sink.clone();
        let count = tokio::spawn(async move {
            let (mut n, mut first, mut last) = (0u64, None, None);
            while let Ok(Ok(_)) =
                tokio::time::timeout(Duration::from_millis(300), sink.recv()).await
            {
                let now = Instant::now();
                first.get_or_insert(now);
                last = Some(now);
                n += 1;
            }
            match (first, last) {
                (Some(a), Some(b)) if b > a => n as f64 / b.duration_since(a).as_secs_f64(),
                _ => 0.0,
            }
        });
        let start = Instant::now();
        let mut i = 0u64;
        while start.elapsed().as_secs_f64() < secs {
            for _ in 0..64 {
                self.vars[(i % 100) as usize].set(&[i; 8]).expect("set");
                i += 1;
            }
            tokio::task::yield_now().await;
        }
        count.await.unwrap_or(0.0)
    }

    async fn close(self) {
        self.echo.abort();
        drop((self.ping, self.pongs, self.vars, self.sink));
        self.a.shutdown().await;
        self.b.shutdown().await;
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

pub fn run() {
    let dir = tempfile::tempdir().expect("temp dir");
    let key_file = dir.path().join("domain.key");
    let key = DomainKey::create_file(&key_file).expect("key file");
    let mut roster = marea::identity::Roster::default();
    for node in ["a", "b"] {
        let id = marea::identity::IdentityKey::create_files(&dir.path().join(format!("{node}.id")))
            .expect("identity key");
        roster.allow(id.public(), vec!["*".into()]);
    }
    let roster_file = dir.path().join("identities.xml");
    std::fs::write(&roster_file, roster.to_xml()).expect("roster");
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&roster_file, std::fs::Permissions::from_mode(0o644))
            .expect("chmod roster");
    }

    metric(
        "auth.wire.position.udp_bytes",
        udp_bytes(&key) as f64,
        "bytes",
    );
    metric(
        "auth.wire.position.serial_bytes",
        serial_bytes(&key),
        "bytes",
    );

    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime");
    rt.block_on(async {
        let port = 30_000 + (std::process::id() % 20_000) as u16;
        let plain = Pair::open("plain", port, None).await;
        let keyed = Pair::open("keyed", port.wrapping_add(1), Some(dir.path())).await;
        let (mut rtt, mut rate) = ([Vec::new(), Vec::new()], [Vec::new(), Vec::new()]);
        // Warm both up, then interleave.
        plain.rtt_p50(500, 1 << 40).await;
        keyed.rtt_p50(500, 1 << 40).await;
        // Each round measures both, back to back (which goes first alternates), and the ratio
        // is the median of the rounds' ratios: the machine's load then weighs on both sides of
        // each ratio alike.
        for round in 0..ROUNDS {
            let base = (round as u64) << 32;
            let order = if round % 2 == 0 { [0, 1] } else { [1, 0] };
            for i in order {
                let p = [&plain, &keyed][i];
                rtt[i].push(p.rtt_p50(RTTS, base).await);
            }
            for i in order {
                let p = [&plain, &keyed][i];
                rate[i].push(p.rate(RATE_SECS).await);
            }
        }
        let ratios = |v: &[Vec<f64>; 2]| -> f64 {
            median(v[1].iter().zip(&v[0]).map(|(k, p)| k / p).collect())
        };
        let (rtt_ratio, rate_ratio) = (ratios(&rtt), ratios(&rate));
        let [rtt_plain, rtt_keyed] = rtt.map(median);
        let [rate_plain, rate_keyed] = rate.map(median);
        metric("auth.udp.var64.rtt_p50_us", rtt_keyed, "us");
        metric("auth.udp.var64.plain_rtt_p50_us", rtt_plain, "us");
        metric("auth.udp.var64.rtt_ratio_to_plain", rtt_ratio, "ratio");
        metric("auth.udp.var64.msgs_per_s", rate_keyed, "msgs/s");
        metric("auth.udp.var64.plain_msgs_per_s", rate_plain, "msgs/s");
        metric("auth.udp.var64.rate_ratio_to_plain", rate_ratio, "ratio");
        plain.close().await;
        keyed.close().await;
    });
}
