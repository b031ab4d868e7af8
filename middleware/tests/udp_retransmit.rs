//! A lone safe message that is lost is retransmitted, even when the peer sends nothing back
//! and nothing else wakes the UDP link's transmit task: the first message in flight arms its
//! timer (it was written inline by the sender, and the task slept with no deadline at all).

use std::sync::Arc;
use std::time::Duration;

use marea::link::arq::ArqConfig;
use marea::link::udp::{UdpLink, UdpLinkOptions};
use marea::link::{Link, LinkHandler, Outgoing, PeerAddr};
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

struct Ignore;

impl LinkHandler for Ignore {
    fn on_message(&self, _: usize, _: PeerAddr, _: &[u8]) {}
    fn on_announce(&self, _: usize, _: PeerAddr, _: &[u8]) {}
    fn on_peer_reset(&self, _: usize, _: PeerAddr) {}
}

#[tokio::test]
async fn a_lost_lone_safe_message_is_retransmitted_without_any_reply() {
    let tasks = TaskTracker::new();
    let cancel = CancellationToken::new();
    let port = 26_000 + (std::process::id() % 20_000) as u16;
    let link = UdpLink::open(
        0,
        UdpLinkOptions {
            name: "a".into(),
            bind: "127.0.0.1:0".parse().unwrap(),
            multicast: std::net::SocketAddrV4::new(std::net::Ipv4Addr::new(239, 255, 77, 6), port),
            interface: std::net::Ipv4Addr::LOCALHOST,
            ttl: 0,
            peers: vec![],
            mtu: 1400,
            arq: ArqConfig::lan(),
            security: None,
        },
        Arc::new(Ignore),
        &tasks,
        cancel.child_token(),
    )
    .unwrap();
    // A "peer" that reads datagrams and never answers: every one it gets is lost to the link.
    let sink = tokio::net::UdpSocket::bind("127.0.0.1:0").await.unwrap();
    let to = PeerAddr::Udp(sink.local_addr().unwrap());
    // Let the transmit task go to sleep with nothing in flight.
    tokio::task::yield_now().await;
    link.send(
        to,
        Outgoing::Safe {
            msg: b"lone".to_vec(),
            done: None,
        },
    );
    let mut buf = [0u8; 2048];
    let first = tokio::time::timeout(Duration::from_secs(5), sink.recv(&mut buf))
        .await
        .expect("first transmission")
        .unwrap();
    let first = buf[..first].to_vec();
    // The retransmission timer (200 ms before any round trip is measured) must fire on its
    // own: nothing else happens on this link.
    let again = tokio::time::timeout(Duration::from_secs(10), sink.recv(&mut buf))
        .await
        .expect("no retransmission of the lost message")
        .unwrap();
    assert_eq!(buf[..again], first[..], "the same datagram again");
    assert!(link.stats().retransmitted >= 1);
    cancel.cancel();
    tasks.close();
    let _ = tokio::time::timeout(Duration::from_secs(5), tasks.wait()).await;
}
