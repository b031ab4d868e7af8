//! The UDP link's safe class against a peer that never answers (a plain socket): a lone lost
//! message is retransmitted, even when nothing else wakes the link's transmit task (the first
//! message in flight arms its timer: it was written inline by the sender, and the task slept
//! with no deadline at all); messages sent while one is unacknowledged gather for the next
//! acknowledgement (or retransmission) unless they fill a datagram, and leave aged by their wait
//! (a call among them carries its caller's time left, not its time at the queue's door).

use std::sync::Arc;
use std::time::Duration;

use marea::link::udp::UdpLink;
use marea::link::{Link, LinkHandler, Outgoing, PeerAddr};
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

mod common;

struct Ignore;

impl LinkHandler for Ignore {
    fn on_message(&self, _: usize, _: PeerAddr, _: &[u8]) {}
    fn on_announce(&self, _: usize, _: PeerAddr, _: &[u8]) {}
    fn on_peer_reset(&self, _: usize, _: PeerAddr) {}
}

/// Records the waits of the safe messages the link ages as they leave its queue.
#[derive(Default)]
struct Ages(std::sync::Mutex<Vec<(Vec<u8>, Duration)>>);

impl LinkHandler for Ages {
    fn on_message(&self, _: usize, _: PeerAddr, _: &[u8]) {}
    fn on_announce(&self, _: usize, _: PeerAddr, _: &[u8]) {}
    fn on_peer_reset(&self, _: usize, _: PeerAddr) {}
    fn age_safe(&self, msg: &mut Vec<u8>, waited: Duration) {
        self.0.lock().unwrap().push((msg.clone(), waited));
    }
    fn ages(&self, _: &[u8]) -> bool {
        true
    }
}

/// A UDP link on loopback (MTU 1,400 for every peer but loopback ones; the test's peer is a
/// loopback address, so its datagrams are up to 60 KiB) whose multicast port is `port`.
fn open_link(
    port: u16,
    handler: Arc<dyn LinkHandler>,
    tasks: &TaskTracker,
    cancel: &CancellationToken,
) -> Arc<UdpLink> {
    UdpLink::open(
        0,
        common::udp_link_options("a", 6, port),
        handler,
        tasks,
        cancel.child_token(),
    )
    .unwrap()
}

/// A link and, as its peer, a plain socket that reads datagrams and never answers: every
/// message it gets is lost to the link.
struct SilentPeer {
    tasks: TaskTracker,
    cancel: CancellationToken,
    link: Arc<UdpLink>,
    sink: tokio::net::UdpSocket,
    to: PeerAddr,
}

impl SilentPeer {
    /// `case` keeps the tests' multicast ports apart.
    async fn new(case: u16) -> SilentPeer {
        SilentPeer::with_handler(case, Arc::new(Ignore)).await
    }

    async fn with_handler(case: u16, handler: Arc<dyn LinkHandler>) -> SilentPeer {
        let tasks = TaskTracker::new();
        let cancel = CancellationToken::new();
        let port = 26_000 + case + (std::process::id() % 20_000) as u16;
        let link = open_link(port, handler, &tasks, &cancel);
        let sink = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
        let to = PeerAddr::Udp(sink.local_addr().unwrap());
        SilentPeer {
            tasks,
            cancel,
            link,
            sink,
            to,
        }
    }

    fn send(&self, msg: &[u8]) {
        self.link.send(
            self.to,
            Outgoing::Safe {
                msg: msg.to_vec().into(),
                done: None,
            },
        );
    }

    /// The next datagram the peer gets, within `within`; panics naming `what` after it.
    async fn recv(&self, within: Duration, what: &str) -> Vec<u8> {
        let mut buf = vec![0u8; 65_536];
        let n = tokio::time::timeout(within, self.sink.recv(&mut buf))
            .await
            .unwrap_or_else(|_| panic!("{what}"))
            .unwrap();
        buf.truncate(n);
        buf
    }

    async fn close(self) {
        self.cancel.cancel();
        self.tasks.close();
        let _ = tokio::time::timeout(Duration::from_secs(5), self.tasks.wait()).await;
    }
}

fn contains(datagram: &[u8], msg: &[u8]) -> bool {
    datagram.windows(msg.len()).any(|w| w == msg)
}

#[tokio::test]
async fn a_lost_lone_safe_message_is_retransmitted_without_any_reply() {
    let p = SilentPeer::new(0).await;
    // Let the transmit task go to sleep with nothing in flight.
    tokio::task::yield_now().await;
    p.send(b"lone");
    let first = p.recv(Duration::from_secs(5), "first transmission").await;
    // The retransmission timer (200 ms before any round trip is measured) must fire on its
    // own: nothing else happens on this link.
    let again = p
        .recv(
            Duration::from_secs(10),
            "no retransmission of the lost message",
        )
        .await;
    assert_eq!(again, first, "the same datagram again");
    assert!(p.link.stats().retransmitted >= 1);
    p.close().await;
}

#[tokio::test]
async fn safe_messages_sent_while_one_is_unacknowledged_leave_together() {
    let p = SilentPeer::new(1).await;
    p.send(b"first message");
    let first = p
        .recv(Duration::from_secs(5), "the first message leaves at once")
        .await;
    assert!(contains(&first, b"first message"));
    // More while the first is unacknowledged (and never will be): they wait for its
    // acknowledgement, so the next datagram is its retransmission, and carries them all.
    // (Three: the timeout shrinks the congestion window to four messages.)
    let later: Vec<Vec<u8>> = (0..3)
        .map(|i| format!("later {i:02}").into_bytes())
        .collect();
    for m in &later {
        p.send(m);
    }
    let second = p.recv(Duration::from_secs(10), "a second datagram").await;
    assert!(
        contains(&second, b"first message"),
        "the later messages left before the first was acknowledged or due again"
    );
    for m in &later {
        assert!(
            contains(&second, m),
            "{} not in the retransmission's datagram",
            String::from_utf8_lossy(m)
        );
    }
    assert_eq!(p.link.stats().frames_out, 2, "two datagrams in all");
    p.close().await;
}

#[tokio::test]
async fn safe_messages_that_fill_a_datagram_do_not_wait_for_an_acknowledgement() {
    let p = SilentPeer::new(2).await;
    p.send(b"first message");
    p.recv(Duration::from_secs(5), "the first message leaves at once")
        .await;
    // More than a loopback datagram's worth (60 KiB) while the first is unacknowledged: a
    // full datagram leaves without waiting, before the first message is due again. (Seven: a
    // peer the node does not know yet gets at most eight queued or in flight.)
    let big = vec![7u8; 9_000];
    for _ in 0..7 {
        p.send(&big);
    }
    let second = p.recv(Duration::from_secs(10), "a second datagram").await;
    assert!(
        !contains(&second, b"first message"),
        "the full datagram waited for the first message's retransmission"
    );
    assert_eq!(p.link.stats().retransmitted, 0);
    assert!(
        second.len() > 45_000,
        "a full datagram, not {} bytes",
        second.len()
    );
    p.close().await;
}

#[tokio::test]
async fn safe_messages_that_waited_leave_aged_by_their_wait() {
    let ages = Arc::new(Ages::default());
    let p = SilentPeer::with_handler(3, ages.clone()).await;
    p.send(b"first message");
    p.recv(Duration::from_secs(5), "the first message leaves at once")
        .await;
    let later: Vec<Vec<u8>> = (0..3)
        .map(|i| format!("later {i:02}").into_bytes())
        .collect();
    for m in &later {
        p.send(m);
    }
    // They wait for the first one's retransmission (200 ms before any round trip is known).
    let second = p.recv(Duration::from_secs(10), "a second datagram").await;
    assert!(later.iter().all(|m| contains(&second, m)));
    let aged = ages.0.lock().unwrap().clone();
    let msgs: Vec<&Vec<u8>> = aged.iter().map(|(m, _)| m).collect();
    assert_eq!(
        msgs,
        later.iter().collect::<Vec<_>>(),
        "each waiting one aged, the first not"
    );
    for (m, waited) in &aged {
        assert!(
            *waited >= Duration::from_millis(100),
            "{} aged by {waited:?} only",
            String::from_utf8_lossy(m)
        );
    }
    p.close().await;
}
