//! One conformance suite generic over [`Link`], run against every link kind: UDP on loopback,
//! serial (the Serial Transport Protocol over an in-memory line at 1 Mbit/s) and shared memory
//! (with the `shm` feature). Each check is written once, against the trait, so every link keeps
//! the same contract.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use marea::link::arq::ArqConfig;
use marea::link::auth::{DomainKey, LinkSecurity};
use marea::link::serial::stp::StpConfig;
use marea::link::serial::SerialLink;
#[cfg(feature = "shm")]
use marea::link::shm::{ShmLink, ShmLinkOptions, ShmWait};
use marea::link::udp::{UdpLink, UdpLinkOptions};
use marea::link::{Link, LinkHandler, LinkSendError, Outgoing, PeerAddr};
use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

/// Records what a link hands to its node.
#[derive(Default)]
struct Recorder {
    messages: Mutex<Vec<(PeerAddr, Vec<u8>)>>,
    announces: Mutex<Vec<(PeerAddr, Vec<u8>)>>,
    changed: Notify,
}

impl LinkHandler for Recorder {
    fn on_message(&self, _link: usize, from: PeerAddr, msg: &[u8]) {
        self.messages.lock().unwrap().push((from, msg.to_vec()));
        self.changed.notify_waiters();
    }
    fn on_announce(&self, _link: usize, from: PeerAddr, msg: &[u8]) {
        self.announces.lock().unwrap().push((from, msg.to_vec()));
        self.changed.notify_waiters();
    }
    fn on_peer_reset(&self, _link: usize, _from: PeerAddr) {}
}

impl Recorder {
    /// Waits until `pred` holds on the recorded messages (bounded).
    async fn wait(&self, what: &str, pred: impl Fn(&[(PeerAddr, Vec<u8>)]) -> bool) {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
        loop {
            let notified = self.changed.notified();
            if pred(&self.messages.lock().unwrap()) {
                return;
            }
            if tokio::time::timeout_at(deadline, notified).await.is_err() {
                panic!("timed out waiting for {what}");
            }
        }
    }

    async fn announced_by_peer(&self, tag: &[u8]) -> PeerAddr {
        let deadline = tokio::time::Instant::now() + Duration::from_secs(20);
        loop {
            let notified = self.changed.notified();
            // A link may hand an announce to `on_announce` or, where discovery shares the data
            // path (serial), to `on_message`; the node treats both alike.
            let announces = self.announces.lock().unwrap().clone();
            let messages = self.messages.lock().unwrap().clone();
            if let Some((from, _)) = announces.iter().chain(&messages).find(|(_, m)| m == tag) {
                return *from;
            }
            if tokio::time::timeout_at(deadline, notified).await.is_err() {
                panic!("no announce {tag:?} received");
            }
        }
    }
}

struct Pair {
    a: Arc<dyn Link>,
    b: Arc<dyn Link>,
    ra: Arc<Recorder>,
    rb: Arc<Recorder>,
    tasks: TaskTracker,
    cancel: CancellationToken,
}

impl Pair {
    /// Each side announces a tag until the other has heard it, which tells each the address it
    /// knows the other by (multicast, point to point or shared-memory discovery).
    async fn addresses(&self) -> (PeerAddr, PeerAddr) {
        let announcing = {
            let (a, b) = (self.a.clone(), self.b.clone());
            let cancel = self.cancel.child_token();
            let c = cancel.clone();
            tokio::spawn(async move {
                while !c.is_cancelled() {
                    a.announce(b"from-a");
                    b.announce(b"from-b");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                }
            });
            cancel
        };
        let b_at_a = self.ra.announced_by_peer(b"from-b").await;
        let a_at_b = self.rb.announced_by_peer(b"from-a").await;
        announcing.cancel();
        // As a node does once a peer's Hello arrived: the addresses are known peers, whose
        // sessions are bound (a session with an unknown address holds only a few messages).
        self.a.confirm_peer(b_at_a);
        self.b.confirm_peer(a_at_b);
        (b_at_a, a_at_b)
    }

    async fn close(self) {
        self.cancel.cancel();
        self.tasks.close();
        let _ = tokio::time::timeout(Duration::from_secs(5), self.tasks.wait()).await;
    }
}

/// A domain key for the keyed instances of the suite.
fn security(encrypt_radio: bool) -> Option<LinkSecurity> {
    Some(LinkSecurity {
        key: DomainKey::from_bytes([0x5A; 32]),
        encrypt_radio,
    })
}

async fn udp_pair(security: Option<LinkSecurity>) -> Pair {
    let tasks = TaskTracker::new();
    let cancel = CancellationToken::new();
    // The keyed pair uses its own group port: the tests of this file run in parallel.
    let port = test_support::multicast_port(u64::from(std::process::id()) + 4_000)
        + u16::from(security.is_some());
    let opts = |name: &str| UdpLinkOptions {
        name: name.into(),
        bind: "127.0.0.1:0".parse().unwrap(),
        multicast: std::net::SocketAddrV4::new(std::net::Ipv4Addr::new(239, 255, 77, 5), port),
        interface: std::net::Ipv4Addr::LOCALHOST,
        ttl: 0,
        peers: vec![],
        mtu: 1400,
        arq: ArqConfig::lan(),
        security: security.clone(),
    };
    let (ra, rb) = (Arc::new(Recorder::default()), Arc::new(Recorder::default()));
    let a = UdpLink::open(0, opts("a"), ra.clone(), &tasks, cancel.child_token()).unwrap();
    let b = UdpLink::open(0, opts("b"), rb.clone(), &tasks, cancel.child_token()).unwrap();
    Pair {
        a,
        b,
        ra,
        rb,
        tasks,
        cancel,
    }
}

async fn serial_pair(security: Option<LinkSecurity>) -> Pair {
    let tasks = TaskTracker::new();
    let cancel = CancellationToken::new();
    let cfg = StpConfig::new(1_000_000, Duration::from_millis(200), 300, 64);
    let (a_to_b_w, a_to_b_r) = tokio::io::duplex(1 << 16);
    let (b_to_a_w, b_to_a_r) = tokio::io::duplex(1 << 16);
    let (ra, rb) = (Arc::new(Recorder::default()), Arc::new(Recorder::default()));
    let a = SerialLink::with_streams_secured(
        0,
        "a",
        (Box::new(b_to_a_r), Box::new(a_to_b_w)),
        cfg,
        security.as_ref(),
        ra.clone(),
        &tasks,
        cancel.child_token(),
    );
    let b = SerialLink::with_streams_secured(
        0,
        "b",
        (Box::new(a_to_b_r), Box::new(b_to_a_w)),
        cfg,
        security.as_ref(),
        rb.clone(),
        &tasks,
        cancel.child_token(),
    );
    Pair {
        a,
        b,
        ra,
        rb,
        tasks,
        cancel,
    }
}

#[cfg(feature = "shm")]
async fn shm_pair(security: Option<LinkSecurity>) -> Pair {
    let tasks = TaskTracker::new();
    let cancel = CancellationToken::new();
    let service = format!(
        "conformance-{}-{}",
        std::process::id(),
        if security.is_some() { "keyed" } else { "plain" }
    );
    let opts = |name: &str| ShmLinkOptions {
        name: name.into(),
        service: service.clone(),
        scan: Duration::from_millis(100),
        wait: ShmWait::Event,
        max_peers: marea::config::ShmConfig::default().max_peers,
        security: security.clone(),
    };
    let (ra, rb) = (Arc::new(Recorder::default()), Arc::new(Recorder::default()));
    let a = ShmLink::open(0, opts("a"), ra.clone(), &tasks, cancel.child_token())
        .await
        .unwrap();
    let b = ShmLink::open(0, opts("b"), rb.clone(), &tasks, cancel.child_token())
        .await
        .unwrap();
    Pair {
        a,
        b,
        ra,
        rb,
        tasks,
        cancel,
    }
}

/// The contract every link keeps.
async fn conformance(pair: Pair) {
    let (b_at_a, a_at_b) = pair.addresses().await;

    // Fast: a message arrives intact, attributed to the sender.
    pair.a.send(
        b_at_a,
        Outgoing::Fast {
            coalesce: Some(1),
            msg: b"fast-1".to_vec(),
        },
    );
    pair.rb
        .wait("a fast message", |m| {
            m.iter().any(|(from, b)| *from == a_at_b && b == b"fast-1")
        })
        .await;

    // Safe: 1000 messages arrive exactly once, in order, and every completion reports success.
    let mut done = Vec::new();
    for i in 0..1000u32 {
        let (tx, rx) = tokio::sync::oneshot::channel();
        let mut msg = b"safe-".to_vec();
        msg.extend_from_slice(&i.to_le_bytes());
        pair.a.send(
            b_at_a,
            Outgoing::Safe {
                msg: msg.into(),
                done: Some(tx.into()),
            },
        );
        done.push(rx);
    }
    let safe_of = |m: &[(PeerAddr, Vec<u8>)]| -> Vec<u32> {
        m.iter()
            .filter(|(_, b)| b.starts_with(b"safe-") && b.len() == 9)
            .map(|(_, b)| u32::from_le_bytes([b[5], b[6], b[7], b[8]]))
            .collect()
    };
    pair.rb
        .wait("1000 safe messages", |m| safe_of(m).len() >= 1000)
        .await;
    for rx in done {
        let r = tokio::time::timeout(Duration::from_secs(20), rx)
            .await
            .expect("completion in time");
        assert_eq!(r.expect("completion sent"), Ok(()));
    }
    assert_eq!(
        safe_of(&pair.rb.messages.lock().unwrap()),
        (0..1000).collect::<Vec<_>>()
    );

    // A safe message larger than one frame or datagram arrives intact.
    let big: Vec<u8> = (0..50_000u32).map(|i| (i % 251) as u8).collect();
    let (tx, rx) = tokio::sync::oneshot::channel();
    pair.b.send(
        a_at_b,
        Outgoing::Safe {
            msg: big.clone().into(),
            done: Some(tx.into()),
        },
    );
    pair.ra
        .wait("a 50 kB safe message", |m| m.iter().any(|(_, b)| *b == big))
        .await;
    assert_eq!(
        tokio::time::timeout(Duration::from_secs(20), rx)
            .await
            .unwrap()
            .unwrap(),
        Ok(())
    );

    // Closing a peer fails what is still unacknowledged, never leaves a completion hanging.
    let mut pending = Vec::new();
    for _ in 0..50 {
        let (tx, rx) = tokio::sync::oneshot::channel();
        pair.a.send(
            b_at_a,
            Outgoing::Safe {
                msg: vec![7; 100].into(),
                done: Some(tx.into()),
            },
        );
        pending.push(rx);
    }
    pair.a.close_peer(b_at_a);
    for rx in pending {
        let r = tokio::time::timeout(Duration::from_secs(10), rx)
            .await
            .expect("completion in time");
        match r {
            Ok(Ok(())) | Ok(Err(LinkSendError::PeerClosed(_))) | Err(_) => {}
            Ok(Err(e)) => panic!("unexpected completion {e:?}"),
        }
    }

    let stats = pair.a.stats();
    assert!(stats.frames_out > 0 && stats.bytes_out > 0, "{stats:?}");
    pair.close().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn udp_link_conforms() {
    conformance(udp_pair(None).await).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn udp_link_with_a_key_conforms() {
    conformance(udp_pair(security(false)).await).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serial_link_with_a_key_conforms() {
    conformance(serial_pair(security(false)).await).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serial_link_with_encryption_conforms() {
    conformance(serial_pair(security(true)).await).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serial_link_conforms() {
    conformance(serial_pair(None).await).await;
}

#[cfg(feature = "shm")]
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shm_link_conforms() {
    conformance(shm_pair(None).await).await;
}

#[cfg(feature = "shm")]
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shm_link_with_a_key_conforms() {
    conformance(shm_pair(security(false)).await).await;
}
