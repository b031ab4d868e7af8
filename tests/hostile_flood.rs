//! Robust without a key: an attacker on the LAN, with real UDP sockets, floods a victim node
//! with forged discovery and session datagrams; the victim keeps its live peers, a node started
//! during or after the attack still finds it, and its counters show what it dropped.

#[path = "common/attacker.rs"]
mod attacker;

use std::net::{Ipv4Addr, SocketAddrV4, UdpSocket};
use std::time::{Duration, Instant};

use marea::{NetworkConfig, Node};

/// A test's own domain and multicast port (tests run in parallel, and other test binaries too).
fn net(test: u16) -> (String, u16) {
    let pid = std::process::id();
    (
        format!("hostile-{test}-{pid}"),
        30_000 + ((pid % 5_000) as u16) * 4 + test,
    )
}

fn cfg(node: &str, domain: &str, port: u16) -> NetworkConfig {
    let group = SocketAddrV4::new(Ipv4Addr::new(239, 255, 77, 13), port);
    attacker::loopback_node_config(node, domain, group, Duration::from_secs(3))
}

fn knows(node: &Node, name: &str) -> bool {
    node.peers().iter().any(|p| p.name == name)
}

async fn discover(a: &Node, b: &Node, within: Duration) -> bool {
    let (an, bn) = (a.name().to_owned(), b.name().to_owned());
    a.wait_until(within, |n| knows(n, &bn)).await && b.wait_until(within, |n| knows(n, &an)).await
}

fn link_stats(node: &Node) -> marea::link::LinkStats {
    node.link_stats()
        .into_iter()
        .next()
        .map(|(_, s)| s)
        .expect("one link")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_heartbeat_flood_from_ten_thousand_ports_does_not_stop_discovery() {
    tokio::time::timeout(Duration::from_secs(60), async {
        let (domain, port) = net(0);
        let victim = Node::open(&cfg("victim", &domain, port)).await.unwrap();
        let friend = Node::open(&cfg("friend", &domain, port)).await.unwrap();
        assert!(discover(&victim, &friend, Duration::from_secs(10)).await);

        // 10,000 heartbeats of invented nodes, each from its own source port: every one made
        // the victim answer with its Hello, and so open a session, which filled the table
        // (4,096) for good.
        let target = attacker::unicast_of(&victim);
        let base = link_stats(&victim).frames_in;
        let sent = tokio::task::block_in_place(|| {
            attacker::flood_heartbeats(target, &domain, 10_000, 500, 0x0bad_0000_0000, |n| {
                attacker::wait_frames_in(&victim, base + n as u64, Duration::from_secs(2));
            })
        })
        .expect("flood sent");
        assert_eq!(sent, 10_000);

        // A node started after the flood finds the victim, and the victim finds it.
        let started = Instant::now();
        let fresh = Node::open(&cfg("fresh", &domain, port)).await.unwrap();
        assert!(
            discover(&victim, &fresh, Duration::from_secs(10)).await,
            "the fresh node and the victim did not discover each other after the flood"
        );
        eprintln!("discovered {:?} after the flood", started.elapsed());
        // The friend was never pushed out.
        assert!(knows(&victim, "friend") && knows(&friend, "victim"));
        // The sessions the flood opened were dropped, and counted: all but the newest are
        // pushed out by newer ones, the rest expire within seconds.
        let dropped = || link_stats(&victim).sessions_expired;
        let deadline = Instant::now() + Duration::from_secs(15);
        while dropped() < 9_900 && Instant::now() < deadline {
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        assert!(
            dropped() >= 9_900,
            "victim's link counted {} sessions dropped",
            dropped()
        );
        // The invented nodes never became peers.
        assert_eq!(victim.peers().len(), 2, "{:?}", victim.peers());
        for n in [fresh, friend, victim] {
            assert!(n.shutdown().await);
        }
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn forged_hellos_never_push_out_a_confirmed_peer() {
    tokio::time::timeout(Duration::from_secs(60), async {
        let (domain, port) = net(1);
        let victim = Node::open(&cfg("victim", &domain, port)).await.unwrap();
        let friend = Node::open(&cfg("friend", &domain, port)).await.unwrap();
        assert!(discover(&victim, &friend, Duration::from_secs(10)).await);

        // 1,200 Hellos of invented nodes (more than the peer table holds), asking for a lease
        // of 49 days, each from its own socket, none of which ever answers.
        let target = attacker::unicast_of(&victim);
        let mut socks = Vec::new();
        for i in 0..1_200u64 {
            let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
            let h = attacker::hello(0x0bad_1000_0000 + i, &domain, &format!("x{i}"), u32::MAX);
            sock.send_to(&h, target).unwrap();
            socks.push(sock);
        }
        let refused = victim
            .wait_until(Duration::from_secs(10), |n| n.refusals().peers_evicted > 0)
            .await;
        assert!(refused, "{:?}", victim.refusals());
        assert!(victim.peers().len() <= 1024, "{}", victim.peers().len());
        // The friend had confirmed (it answered in a session): it stays, both ways.
        assert!(knows(&victim, "friend") && knows(&friend, "victim"));
        // And a new real node still gets in.
        let fresh = Node::open(&cfg("fresh", &domain, port)).await.unwrap();
        assert!(discover(&victim, &fresh, Duration::from_secs(10)).await);
        assert!(knows(&victim, "friend"));
        drop(socks);
        for n in [fresh, friend, victim] {
            assert!(n.shutdown().await);
        }
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_declared_pattern_of_repeated_double_wildcards_is_counted_and_the_peer_kept() {
    tokio::time::timeout(Duration::from_secs(30), async {
        let (domain, port) = net(2);
        let victim = Node::open(&cfg("victim", &domain, port)).await.unwrap();
        let target = attacker::unicast_of(&victim);
        let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
        sock.send_to(
            &attacker::hello(0x0bad_2000_0000, &domain, "mallory", 3000),
            target,
        )
        .unwrap();
        assert!(
            victim
                .wait_until(Duration::from_secs(5), |n| knows(n, "mallory"))
                .await
        );
        // The measured attack: `**/**/…/zz` (within the byte bound here, so the segment and
        // repetition checks are what refuse it).
        let pattern = format!("{}zz", "**/".repeat(40));
        sock.send_to(&attacker::interest_batch(7, &pattern), target)
            .unwrap();
        let counted = victim
            .wait_until(Duration::from_secs(5), |n| {
                n.refusals().bad_declarations == 1
            })
            .await;
        assert!(counted, "{:?}", victim.refusals());
        assert!(knows(&victim, "mallory"), "the peer is kept");
        assert!(victim.shutdown().await);
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_peer_that_never_acknowledges_is_let_go_after_the_retry_limit() {
    tokio::time::timeout(Duration::from_secs(60), async {
        let (domain, port) = net(3);
        let victim = Node::open(&cfg("victim", &domain, port)).await.unwrap();
        let target = attacker::unicast_of(&victim);
        // A forged node that keeps its lease alive with heartbeats but never acknowledges the
        // session the victim opens towards it (a spoofed address would do the same).
        let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
        let id = 0x0bad_3000_0000;
        sock.send_to(&attacker::hello(id, &domain, "ghost", 3000), target)
            .unwrap();
        let hb = attacker::heartbeat(id, attacker::domain_hash(&domain));
        let beat = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(true));
        let b = beat.clone();
        let beating = std::thread::spawn(move || {
            while b.load(std::sync::atomic::Ordering::Relaxed) {
                let _ = sock.send_to(&hb, target);
                std::thread::sleep(Duration::from_millis(100));
            }
        });
        assert!(
            victim
                .wait_until(Duration::from_secs(5), |n| knows(n, "ghost"))
                .await
        );
        let gone = victim
            .wait_until(Duration::from_secs(30), |n| !knows(n, "ghost"))
            .await;
        beat.store(false, std::sync::atomic::Ordering::Relaxed);
        let _ = beating.join();
        assert!(gone, "the victim kept a peer that never acknowledged");
        assert!(link_stats(&victim).sessions_given_up >= 1);
        assert!(victim.shutdown().await);
    })
    .await
    .expect("test finished in time");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn heartbeats_of_an_unknown_node_queue_a_bounded_number_of_answers() {
    tokio::time::timeout(Duration::from_secs(30), async {
        let (domain, port) = net(4);
        let victim = Node::open(&cfg("victim", &domain, port)).await.unwrap();
        let target = attacker::unicast_of(&victim);
        let base = link_stats(&victim).frames_in;
        // 2,000 heartbeats of one invented node from one socket that never answers: each
        // used to queue another Hello for it, kept until acknowledged (never).
        let sock = UdpSocket::bind("127.0.0.1:0").unwrap();
        let hb = attacker::heartbeat(0x0bad_4000_0000, attacker::domain_hash(&domain));
        tokio::task::block_in_place(|| {
            for i in 0..2_000u64 {
                sock.send_to(&hb, target).unwrap();
                if i % 200 == 199 {
                    attacker::wait_frames_in(&victim, base + i + 1, Duration::from_secs(2));
                }
            }
        });
        assert!(attacker::wait_frames_in(
            &victim,
            base + 2_000,
            Duration::from_secs(5)
        ));
        let queued = link_stats(&victim).safe_queued;
        assert!(
            queued <= 8,
            "{queued} safe messages queued for an unknown address"
        );
        assert!(victim.peers().is_empty());
        assert!(victim.shutdown().await);
    })
    .await
    .expect("test finished in time");
}
