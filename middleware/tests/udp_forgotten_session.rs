//! Two UDP links on loopback where one forgets the other's session (what a node does when it
//! drops a peer: its lease ran out while the peer lived on, under load). The forgetting side
//! says so at the first safe message it cannot read, and the sender starts a new session at
//! once: before, it retransmitted into the void until its retry limit (10 s), then gave the
//! peer up, and at 200 nodes on one host those give-ups fed each other until no call from
//! the ground got through.

use std::sync::Arc;
use std::time::Duration;

use marea::link::udp::UdpLink;
use marea::link::{Link, LinkHandler, LinkSendError, Outgoing, PeerAddr};
use tokio::sync::mpsc;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

mod common;

/// What a link's handler saw, in order.
#[derive(Debug, PartialEq, Eq)]
enum Seen {
    Message(Vec<u8>),
    Reset,
    Unreachable,
}

struct Record(mpsc::UnboundedSender<Seen>);

impl LinkHandler for Record {
    fn on_message(&self, _: usize, _: PeerAddr, msg: &[u8]) {
        let _ = self.0.send(Seen::Message(msg.to_vec()));
    }
    fn on_announce(&self, _: usize, _: PeerAddr, _: &[u8]) {}
    fn on_peer_reset(&self, _: usize, _: PeerAddr) {
        let _ = self.0.send(Seen::Reset);
    }
    fn on_peer_unreachable(&self, _: usize, _: PeerAddr) {
        let _ = self.0.send(Seen::Unreachable);
    }
}

struct End {
    link: Arc<UdpLink>,
    seen: mpsc::UnboundedReceiver<Seen>,
}

impl End {
    /// `port`: the multicast port (unused by the test, kept apart from other tests').
    fn open(port: u16, tasks: &TaskTracker, cancel: &CancellationToken) -> End {
        let (tx, seen) = mpsc::unbounded_channel();
        let link = UdpLink::open(
            0,
            common::udp_link_options("lan", 7, port),
            Arc::new(Record(tx)),
            tasks,
            cancel.child_token(),
        )
        .unwrap();
        End { link, seen }
    }

    fn addr(&self) -> PeerAddr {
        PeerAddr::Udp(self.link.local_socket_addr())
    }

    /// Sends a safe message to `to`; its outcome arrives on the returned channel.
    fn send(
        &self,
        to: PeerAddr,
        msg: &[u8],
    ) -> tokio::sync::oneshot::Receiver<Result<(), LinkSendError>> {
        let (done, outcome) = tokio::sync::oneshot::channel();
        self.link.send(
            to,
            Outgoing::Safe {
                msg: msg.to_vec().into(),
                done: Some(done.into()),
            },
        );
        outcome
    }

    /// The next thing the handler saw, within `within`; panics naming `what` after it.
    async fn next(&mut self, within: Duration, what: &str) -> Seen {
        tokio::time::timeout(within, self.seen.recv())
            .await
            .unwrap_or_else(|_| panic!("{what}: nothing within {within:?}"))
            .expect("the handler lives as long as the link")
    }
}

#[tokio::test]
async fn a_sender_whose_session_the_receiver_forgot_starts_a_new_one_at_once() {
    let tasks = TaskTracker::new();
    let cancel = CancellationToken::new();
    let port = 27_000 + (std::process::id() % 20_000) as u16;
    let mut a = End::open(port, &tasks, &cancel);
    let mut b = End::open(port, &tasks, &cancel);
    let within = Duration::from_secs(5);

    // A session from a to b, acknowledged: a's later datagrams carry no SYN.
    let first = a.send(b.addr(), b"first");
    assert_eq!(
        b.next(within, "the first message").await,
        Seen::Message(b"first".to_vec())
    );
    let outcome = tokio::time::timeout(within, first).await;
    assert!(
        matches!(outcome, Ok(Ok(Ok(())))),
        "the first message acknowledged: {outcome:?}"
    );

    // b forgets a, as a node does when it drops a peer.
    b.link.close_peer(a.addr());

    // a's next message cannot be read by b: b says so, and a starts over well before its
    // retry limit (10 s) would have it give b up.
    let lost = a.send(b.addr(), b"second");
    assert_eq!(
        a.next(Duration::from_secs(3), "a told that b forgot its session")
            .await,
        Seen::Reset,
        "a learns that b forgot it, not that b is unreachable"
    );
    let outcome = tokio::time::timeout(within, lost).await;
    assert!(
        matches!(outcome, Ok(Ok(Err(LinkSendError::PeerClosed(_))))),
        "the message b dropped fails as the session's end, not as retries exhausted: {outcome:?}"
    );

    // The new session works: the next message arrives and is acknowledged.
    let third = a.send(b.addr(), b"third");
    assert_eq!(
        b.next(within, "a message in the new session").await,
        Seen::Message(b"third".to_vec())
    );
    let outcome = tokio::time::timeout(within, third).await;
    assert!(
        matches!(outcome, Ok(Ok(Ok(())))),
        "the new session's message acknowledged: {outcome:?}"
    );
    assert_eq!(a.link.stats().sessions_given_up, 0);

    cancel.cancel();
    tasks.close();
    let _ = tokio::time::timeout(Duration::from_secs(5), tasks.wait()).await;
}
