//! Random, truncated and oversized datagrams sent at a node's ports are counted and dropped,
//! and the node keeps serving its subscribers.

mod common;

use std::net::{Ipv4Addr, SocketAddrV4, UdpSocket};
use std::time::Duration;

use marea::link::datagram::DatagramWriter;
use marea::{NetworkConfig, Node};
use proptest::prelude::*;

fn cfg(node: &str, domain: &str, port: u16) -> NetworkConfig {
    common::loopback_config(node, domain, 2, port, Duration::from_millis(5000))
}

/// Datagrams an attacker or a broken device might send: random bytes, valid-looking headers
/// with lying lengths, truncated real frames, and oversized ones.
fn hostile() -> impl Strategy<Value = Vec<u8>> {
    prop_oneof![
        proptest::collection::vec(any::<u8>(), 0..64),
        proptest::collection::vec(any::<u8>(), 1000..9000),
        (any::<u8>(), proptest::collection::vec(any::<u8>(), 0..40)).prop_map(|(t, rest)| {
            let mut v = vec![0xA1, (t % 5) + 1, 0xFF, 0xFF, 0xFF, 0x0F];
            v.extend(rest);
            v
        }),
        proptest::collection::vec(any::<u8>(), 0..40).prop_map(|rest| {
            let mut v = vec![0xA2];
            v.extend(rest);
            v
        }),
        (1usize..30).prop_map(|cut| {
            let mut w = DatagramWriter::new(1400);
            w.push_syn(7);
            w.push_safe(0, &[5, 1, 32, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10]);
            let d = w.take();
            d[..cut.min(d.len())].to_vec()
        }),
    ]
}

#[test]
fn hostile_datagrams_are_dropped_and_the_node_keeps_serving() {
    let rt = tokio::runtime::Runtime::new().unwrap();
    let domain = format!("garbage-{}", std::process::id());
    let port = test_support::multicast_port(u64::from(std::process::id()) + 1_000);
    let (target, publisher, var, sub) = rt.block_on(async {
        let target = Node::open(&cfg("target", &domain, port)).await.unwrap();
        let publisher = Node::open(&cfg("publisher", &domain, port)).await.unwrap();
        let var = publisher
            .service("pub")
            .unwrap()
            .publish_variable::<u64>("counter")
            .unwrap();
        let sub = target
            .service("sub")
            .unwrap()
            .subscribe_variable::<u64>("pub/counter")
            .unwrap();
        assert!(
            var.wait_remote_subscribers(1, Duration::from_secs(10))
                .await
        );
        (target, publisher, var, sub)
    });
    let addr = target.link_addrs()[0]
        .trim_start_matches("udp://")
        .to_owned();
    let attacker = UdpSocket::bind("127.0.0.1:0").unwrap();
    let sent = std::cell::Cell::new(0u64);
    let mut runner = proptest::test_runner::TestRunner::new(ProptestConfig::with_cases(300));
    runner
        .run(&hostile(), |bytes| {
            attacker.send_to(&bytes, &addr).unwrap();
            attacker
                .send_to(
                    &bytes,
                    SocketAddrV4::new(Ipv4Addr::new(239, 255, 77, 2), port),
                )
                .ok();
            sent.set(sent.get() + 1);
            Ok(())
        })
        .unwrap();
    rt.block_on(async {
        // Still serving: a value published after the garbage reaches the subscriber (older
        // values may still be queued ahead of it; the subscription keeps the newest).
        var.set(&1000).unwrap();
        let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
        let mut last = 0;
        while last < 1000 && tokio::time::Instant::now() < deadline {
            last = sub
                .recv_timeout(Duration::from_secs(10))
                .await
                .unwrap()
                .value;
        }
        assert!(
            last >= 1000,
            "subscriber stopped receiving after garbage (last {last})"
        );
    });
    let stats = &target.link_stats()[0].1;
    let (undecodable, unknown) = target.dropped_input();
    let dropped = stats.corrupt + undecodable + unknown;
    assert_eq!(sent.get(), 300);
    assert!(
        dropped > 0,
        "hostile datagrams were not counted: link {stats:?}, node ({undecodable}, {unknown})"
    );
    rt.block_on(async {
        drop((var, sub));
        target.shutdown().await;
        publisher.shutdown().await;
    });
}
