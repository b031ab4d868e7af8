//! The shared-memory link against real iceoryx2 in one process: discovery, both classes,
//! bulk messages, both ways of waiting, a stalled reader and closing a peer.

use super::*;

/// What a link delivered, in order.
#[derive(Debug, Clone, PartialEq, Eq)]
enum Got {
    Msg(PeerAddr, Vec<u8>),
    Announce(PeerAddr, Vec<u8>),
    Reset(PeerAddr),
}

struct Collect(mpsc::Sender<Got>);

impl LinkHandler for Collect {
    fn on_message(&self, _: usize, from: PeerAddr, msg: &[u8]) {
        let _ = self.0.send(Got::Msg(from, msg.to_vec()));
    }
    fn on_announce(&self, _: usize, from: PeerAddr, msg: &[u8]) {
        let _ = self.0.send(Got::Announce(from, msg.to_vec()));
    }
    fn on_peer_reset(&self, _: usize, from: PeerAddr) {
        let _ = self.0.send(Got::Reset(from));
    }
}

fn unique_service(tag: &str) -> String {
    format!("t{tag}{}x{:08x}", std::process::id(), rand::random::<u32>())
}

async fn open_link(
    service: &str,
    tasks: &TaskTracker,
    cancel: &CancellationToken,
) -> (Arc<ShmLink>, mpsc::Receiver<Got>) {
    open_link_waiting(service, ShmWait::Event, tasks, cancel).await
}

async fn open_link_waiting(
    service: &str,
    wait: ShmWait,
    tasks: &TaskTracker,
    cancel: &CancellationToken,
) -> (Arc<ShmLink>, mpsc::Receiver<Got>) {
    open_link_admitting(service, wait, MAX_PEERS, tasks, cancel).await
}

/// Peers a test link admits: as many as a node's `<shm>` by default, more than any test here
/// opens (except the test of the limit itself, which sets its own).
const MAX_PEERS: usize = 16;

async fn open_link_admitting(
    service: &str,
    wait: ShmWait,
    max_peers: usize,
    tasks: &TaskTracker,
    cancel: &CancellationToken,
) -> (Arc<ShmLink>, mpsc::Receiver<Got>) {
    let (tx, rx) = mpsc::channel();
    let link = ShmLink::open(
        0,
        ShmLinkOptions {
            name: "shm0".into(),
            service: service.into(),
            scan: Duration::from_millis(200),
            wait,
            max_peers,
            security: None,
        },
        Arc::new(Collect(tx)),
        tasks,
        cancel.child_token(),
    )
    .await
    .expect("shm link opens");
    (link, rx)
}

/// Next delivery that is not an announcement, within 5 s.
fn next_msg(rx: &mpsc::Receiver<Got>) -> Got {
    let deadline = Instant::now() + Duration::from_secs(5);
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        match rx.recv_timeout(left) {
            Ok(Got::Announce(..)) => continue,
            Ok(g) => return g,
            Err(e) => panic!("nothing delivered: {e}"),
        }
    }
}

fn safe(
    msg: Vec<u8>,
) -> (
    Outgoing,
    tokio::sync::oneshot::Receiver<Result<(), LinkSendError>>,
) {
    let (tx, rx) = tokio::sync::oneshot::channel();
    (
        Outgoing::Safe {
            msg: msg.into(),
            done: Some(tx.into()),
        },
        rx,
    )
}

async fn stop(tasks: TaskTracker, cancel: CancellationToken) {
    cancel.cancel();
    tasks.close();
    tokio::time::timeout(Duration::from_secs(5), tasks.wait())
        .await
        .expect("receive threads stop");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn announce_reaches_a_node_started_earlier_and_later() {
    let svc = unique_service("ann");
    let (tasks, cancel) = (TaskTracker::new(), CancellationToken::new());
    let (a, arx) = open_link(&svc, &tasks, &cancel).await;
    let (b, brx) = open_link(&svc, &tasks, &cancel).await;
    // b connected to a when it opened; a connects to b when it first hears from it.
    b.announce(b"hello from b");
    let got = arx.recv_timeout(Duration::from_secs(5)).expect("a hears b");
    assert_eq!(
        got,
        Got::Announce(PeerAddr::Shm(b.id()), b"hello from b".to_vec())
    );
    a.send(
        PeerAddr::Shm(b.id()),
        Outgoing::Fast {
            coalesce: None,
            msg: b"x".to_vec(),
        },
    );
    assert_eq!(
        next_msg(&brx),
        Got::Msg(PeerAddr::Shm(a.id()), b"x".to_vec())
    );
    a.announce(b"hello from a");
    let deadline = Instant::now() + Duration::from_secs(5);
    loop {
        match brx.recv_timeout(deadline.saturating_duration_since(Instant::now())) {
            Ok(Got::Announce(from, m)) if m == b"hello from a" => {
                assert_eq!(from, PeerAddr::Shm(a.id()));
                break;
            }
            Ok(_) => continue,
            Err(e) => panic!("b never heard a's announcement: {e}"),
        }
    }
    stop(tasks, cancel).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn safe_messages_arrive_once_in_order_and_are_acknowledged() {
    let svc = unique_service("safe");
    let (tasks, cancel) = (TaskTracker::new(), CancellationToken::new());
    let (a, _arx) = open_link(&svc, &tasks, &cancel).await;
    let (b, brx) = open_link(&svc, &tasks, &cancel).await;
    let n = 5000u32;
    let mut acks = Vec::new();
    for i in 0..n {
        // Every 500th message spans several frames.
        let len = if i % 500 == 0 { 3 * FRAME_MAX + 17 } else { 8 };
        let mut m = vec![(i % 251) as u8; len];
        m[..4].copy_from_slice(&i.to_le_bytes());
        let (out, done) = safe(m);
        a.send(PeerAddr::Shm(b.id()), out);
        acks.push(done);
    }
    for i in 0..n {
        let Got::Msg(from, m) = next_msg(&brx) else {
            panic!("unexpected delivery");
        };
        assert_eq!(from, PeerAddr::Shm(a.id()));
        assert_eq!(u32::from_le_bytes([m[0], m[1], m[2], m[3]]), i);
        let len = if i % 500 == 0 { 3 * FRAME_MAX + 17 } else { 8 };
        assert_eq!(m.len(), len);
        assert!(m[4..].iter().all(|&x| x == (i % 251) as u8));
    }
    for d in acks {
        acknowledged(d, Duration::from_secs(5)).await;
    }
    assert_eq!(b.stats().duplicates, 0);
    stop(tasks, cancel).await;
}

/// Waits up to `within` for `done` to report the message acknowledged.
async fn acknowledged(
    done: tokio::sync::oneshot::Receiver<Result<(), LinkSendError>>,
    within: Duration,
) {
    let r = tokio::time::timeout(within, done).await;
    assert_eq!(
        r.expect("acknowledged in time").expect("completion sent"),
        Ok(())
    );
}

/// `from` sends `to` the safe message `msg`: it is the next delivery on `to_rx` and is
/// acknowledged.
async fn delivered(from: &ShmLink, to: &ShmLink, to_rx: &mpsc::Receiver<Got>, msg: &[u8]) {
    let (out, done) = safe(msg.to_vec());
    from.send(PeerAddr::Shm(to.id()), out);
    assert_eq!(
        next_msg(to_rx),
        Got::Msg(PeerAddr::Shm(from.id()), msg.to_vec())
    );
    acknowledged(done, Duration::from_secs(5)).await;
}

/// `maxPeers` bounds a link's peers both ways: its inbox admits that many writers and it
/// writes to that many peers. A link with other limits meets it; one beyond them does not, and
/// what it is refused fails at once on the full side instead of waiting.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_link_admits_max_peers_and_links_with_other_limits_meet() {
    let svc = unique_service("max");
    let (tasks, cancel) = (TaskTracker::new(), CancellationToken::new());
    let (a, arx) = open_link_admitting(&svc, ShmWait::Event, 1, &tasks, &cancel).await;
    let (b, brx) = open_link(&svc, &tasks, &cancel).await;
    // b (16 peers) and a (1) meet both ways.
    delivered(&b, &a, &arx, b"b to a").await;
    delivered(&a, &b, &brx, b"a to b").await;
    // c comes third: a has no room for it, b has.
    let (c, crx) = open_link(&svc, &tasks, &cancel).await;
    let (out, refused) = safe(b"a to c".to_vec());
    a.send(PeerAddr::Shm(c.id()), out);
    let r = tokio::time::timeout(Duration::from_secs(5), refused).await;
    assert!(
        matches!(r, Ok(Ok(Err(LinkSendError::PeerClosed(_))))),
        "a's send to a peer beyond maxPeers fails at once: {r:?}"
    );
    // c's first scan (before it opened) found a's inbox full. Had it been let in, this would be
    // written and a woken here, and reach a before anything below.
    let (out, _never) = safe(b"c to a".to_vec());
    c.send(PeerAddr::Shm(a.id()), out);
    delivered(&c, &b, &brx, b"c to b").await;
    delivered(&b, &c, &crx, b"b to c").await;
    // And a still hears b, and only b.
    delivered(&b, &a, &arx, b"b to a again").await;
    while let Ok(g) = arx.try_recv() {
        assert!(
            !matches!(g, Got::Msg(from, _) if from == PeerAddr::Shm(c.id())),
            "a heard c"
        );
    }
    stop(tasks, cancel).await;
}

/// A message of `len` bytes tagged with the writer and its index.
fn tagged_message(writer: u8, i: u32, len: usize) -> Vec<u8> {
    let mut m: Vec<u8> = (0..len)
        .map(|k| (k as u32).wrapping_mul(31).wrapping_add(i) as u8)
        .collect();
    m[0] = writer;
    m[1..5].copy_from_slice(&i.to_le_bytes());
    m
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn large_messages_of_two_writers_cross_the_bulk_inbox_whole_and_in_order() {
    let svc = unique_service("bulk");
    let (tasks, cancel) = (TaskTracker::new(), CancellationToken::new());
    let (a, _arx) = open_link(&svc, &tasks, &cancel).await;
    let (c, _crx) = open_link(&svc, &tasks, &cancel).await;
    let (b, brx) = open_link(&svc, &tasks, &cancel).await;
    let to = PeerAddr::Shm(b.id());
    // Sizes around every boundary: inline, one bulk sample, several, small again.
    let sizes = [
        10,
        FRAME_MAX - frame::SEQUENCED,
        FRAME_MAX - frame::SEQUENCED + 1,
        BULK_MAX - frame::SEQUENCED,
        BULK_MAX - frame::SEQUENCED + 1,
        3 * BULK_MAX + 5,
        FILE_CHUNK + 40,
        7,
    ];
    let n = 40u32;
    let mut acks = Vec::new();
    // Both writers at once, so the reader meets one writer's bodies while looking for the
    // other's.
    for i in 0..n {
        let len = sizes[i as usize % sizes.len()];
        for (tag, w) in [(b'a', &a), (b'c', &c)] {
            let (out, done) = safe(tagged_message(tag, i, len));
            w.send(to, out);
            acks.push(done);
        }
        if i % 3 == 0 {
            // Fast messages too large for a frame ride the same path.
            a.send(
                to,
                Outgoing::Fast {
                    coalesce: None,
                    msg: tagged_message(b'f', i, 2 * BULK_MAX),
                },
            );
        }
    }
    let mut next = HashMap::from([(b'a', 0u32), (b'c', 0u32), (b'f', 0u32)]);
    while next[&b'a'] < n || next[&b'c'] < n {
        let Got::Msg(_, m) = next_msg(&brx) else {
            panic!("unexpected delivery");
        };
        let i = u32::from_le_bytes([m[1], m[2], m[3], m[4]]);
        let expected = next.get_mut(&m[0]).expect("a known writer");
        assert!(i >= *expected, "writer {} went back to {i}", m[0] as char);
        if m[0] != b'f' {
            assert_eq!(i, *expected, "writer {} skipped", m[0] as char);
            assert_eq!(m.len(), sizes[i as usize % sizes.len()]);
        }
        assert_eq!(m, tagged_message(m[0], i, m.len()), "content of {i}");
        *expected = i + 1;
    }
    for d in acks {
        acknowledged(d, Duration::from_secs(10)).await;
    }
    assert_eq!(b.stats().corrupt, 0);
    assert_eq!(b.stats().duplicates, 0);
    stop(tasks, cancel).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_sleeping_reader_never_misses_a_wake_up() {
    let svc = unique_service("wake");
    let (tasks, cancel) = (TaskTracker::new(), CancellationToken::new());
    let (a, _arx) = open_link(&svc, &tasks, &cancel).await;
    let (c, _crx) = open_link(&svc, &tasks, &cancel).await;
    let (b, _brx) = open_link(&svc, &tasks, &cancel).await;
    let to = PeerAddr::Shm(b.id());
    // Two writers, one message at a time each: the reader falls asleep between most
    // messages and the writers' notifications race with its waking. A wake-up lost for
    // good would leave a message unacknowledged.
    let writer = |w: Arc<ShmLink>| async move {
        for i in 0..3000u32 {
            let (out, done) = safe(i.to_le_bytes().to_vec());
            w.send(to, out);
            let r = tokio::time::timeout(Duration::from_secs(5), done).await;
            assert_eq!(
                r.unwrap_or_else(|_| panic!("message {i} never acknowledged"))
                    .expect("completion sent"),
                Ok(())
            );
        }
    };
    let (ra, rc) = tokio::join!(
        tokio::spawn(writer(a.clone())),
        tokio::spawn(writer(c.clone()))
    );
    ra.expect("writer a");
    rc.expect("writer c");
    stop(tasks, cancel).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_polling_reader_is_never_notified_and_still_gets_everything() {
    let svc = unique_service("spin");
    let (tasks, cancel) = (TaskTracker::new(), CancellationToken::new());
    let (a, arx) = open_link(&svc, &tasks, &cancel).await;
    let (b, brx) = open_link_waiting(&svc, ShmWait::Spin, &tasks, &cancel).await;
    let (to_b, to_a) = (PeerAddr::Shm(b.id()), PeerAddr::Shm(a.id()));
    delivered(&a, &b, &brx, b"first").await;
    // a learnt from b's inbox that b polls, and b that a sleeps.
    let spins = |from: &ShmLink, to: u64| {
        from.peer(to, false)
            .and_then(|p| lock(&p).conn.as_ref().map(|c| c.spins))
    };
    assert_eq!(spins(&a, b.id()), Some(true));
    b.send(
        to_a,
        Outgoing::Fast {
            coalesce: None,
            msg: b"back".to_vec(),
        },
    );
    assert_eq!(next_msg(&arx), Got::Msg(to_b, b"back".to_vec()));
    assert_eq!(spins(&b, a.id()), Some(false));
    // After an idle period (no event marks it: the reader just stops seeing frames) the
    // reader parks between polls, and still picks messages up.
    tokio::time::sleep(YIELD_UNTIL * 3).await;
    for i in 0..200u32 {
        let (out, _) = safe(i.to_le_bytes().to_vec());
        a.send(to_b, out);
    }
    a.send(
        to_b,
        Outgoing::Fast {
            coalesce: None,
            msg: vec![9; 3 * BULK_MAX],
        },
    );
    for i in 0..200u32 {
        assert_eq!(next_msg(&brx), Got::Msg(to_a, i.to_le_bytes().to_vec()));
    }
    assert_eq!(next_msg(&brx), Got::Msg(to_a, vec![9; 3 * BULK_MAX]));
    stop(tasks, cancel).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_reader_that_stops_never_blocks_the_writer() {
    let svc = unique_service("stall");
    let (tasks, cancel) = (TaskTracker::new(), CancellationToken::new());
    let (a, _arx) = open_link(&svc, &tasks, &cancel).await;
    // b's handler blocks until released: its receive thread stops reading.
    let (gate_tx, gate_rx) = std::sync::mpsc::channel::<()>();
    let (tx, brx) = mpsc::channel();
    let (stalled_tx, stalled_rx) = std::sync::mpsc::channel::<()>();
    struct Stuck(Mutex<mpsc::Receiver<()>>, Collect, Mutex<mpsc::Sender<()>>);
    impl LinkHandler for Stuck {
        fn on_message(&self, l: usize, from: PeerAddr, msg: &[u8]) {
            if msg == b"stall" {
                let _ = lock(&self.2).send(());
                let _ = lock(&self.0).recv_timeout(Duration::from_secs(20));
            }
            self.1.on_message(l, from, msg);
        }
        fn on_announce(&self, _: usize, _: PeerAddr, _: &[u8]) {}
        fn on_peer_reset(&self, l: usize, from: PeerAddr) {
            self.1.on_peer_reset(l, from);
        }
    }
    let b = ShmLink::open(
        0,
        ShmLinkOptions {
            name: "shm0".into(),
            service: svc.clone(),
            scan: Duration::from_millis(200),
            wait: ShmWait::Event,
            max_peers: MAX_PEERS,
            security: None,
        },
        Arc::new(Stuck(
            Mutex::new(gate_rx),
            Collect(tx),
            Mutex::new(stalled_tx),
        )),
        &tasks,
        cancel.child_token(),
    )
    .await
    .expect("opens");
    let to = PeerAddr::Shm(b.id());
    a.send(
        to,
        Outgoing::Fast {
            coalesce: None,
            msg: b"stall".to_vec(),
        },
    );
    let tagged = |tag: u8, i: u32| {
        let mut m = vec![tag];
        m.extend_from_slice(&i.to_le_bytes());
        m
    };
    // Only once b's receive thread is really stuck does the burst test a stopped reader.
    stalled_rx
        .recv_timeout(Duration::from_secs(20))
        .expect("b's reader reached the stall");
    let started = Instant::now();
    for i in 0..20_000u32 {
        a.send(
            to,
            Outgoing::Fast {
                coalesce: Some(1),
                msg: tagged(b'f', i),
            },
        );
    }
    // Safe messages long enough that 1,000 of them (packed 3 to a frame) overfill the inbox.
    let mut acks = Vec::new();
    for i in 0..1000u32 {
        let mut m = tagged(b's', i);
        m.resize(2048, 0);
        let (out, done) = safe(m);
        a.send(to, out);
        acks.push(done);
    }
    assert!(
        started.elapsed() < Duration::from_secs(5),
        "sending blocked"
    );
    assert!(a.stats().retransmitted > 0, "the safe inbox filled up");
    let _ = gate_tx.send(());
    // Every safe message arrives once, in order; the newest fast value survives overflow.
    let mut next_safe = 0u32;
    let mut last_fast = 0u32;
    while next_safe < 1000 || last_fast < 19_999 {
        let Got::Msg(_, m) = next_msg(&brx) else {
            continue;
        };
        if m == b"stall" {
            continue;
        }
        let v = u32::from_le_bytes([m[1], m[2], m[3], m[4]]);
        match m[0] {
            b's' => {
                assert_eq!(v, next_safe);
                next_safe += 1;
            }
            _ => {
                assert!(v >= last_fast);
                last_fast = v;
            }
        }
    }
    for d in acks {
        acknowledged(d, Duration::from_secs(5)).await;
    }
    stop(tasks, cancel).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn closing_a_peer_fails_what_it_did_not_acknowledge() {
    let svc = unique_service("close");
    let (tasks, cancel) = (TaskTracker::new(), CancellationToken::new());
    let (a, _arx) = open_link(&svc, &tasks, &cancel).await;
    // A peer that never existed: the message waits for an inbox that never opens.
    let ghost = PeerAddr::Shm(0x1234);
    let (out, done) = safe(b"lost".to_vec());
    a.send(ghost, out);
    a.close_peer(ghost);
    let r = tokio::time::timeout(Duration::from_secs(5), done).await;
    assert!(matches!(r, Ok(Ok(Err(LinkSendError::PeerClosed(_))))));
    stop(tasks, cancel).await;
}
