//! Discovery repairs a lost introduction. A node that registers a peer introduces itself to it
//! once (its Hello and declarations); if that introduction is lost (a radio, a peer whose link
//! was not open yet), the peer hears only its heartbeats and answers each with a Hello of its
//! own. The node, which knows the peer, must take such a Hello as "I do not know you" and
//! introduce itself again, or the two stay half-known for good (the peer dropping everything
//! the node sends as from an unknown sender). Here the peer is a socket speaking the protocol
//! (`common/attacker.rs`), the node a real one on loopback UDP.

#[path = "common/attacker.rs"]
mod attacker;

use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4};
use std::time::Duration;

use attacker::{unicast_of, Forger};
use marea::protocol::Message;
use marea::{NetworkConfig, Node};

const PEER_ID: u64 = 0xF00D_0000_0000_0001;

fn cfg(domain: &str) -> NetworkConfig {
    let port = test_support::multicast_port(u64::from(std::process::id()));
    let group = SocketAddrV4::new(Ipv4Addr::new(239, 255, 77, 17), port);
    attacker::loopback_node_config("node", domain, group, Duration::from_secs(5))
}

/// The peer's Hello: a first contact, or (`asks_introduction`) the answer to a heartbeat of a
/// node it does not know.
fn hello(domain: &str, asks_introduction: bool) -> Message {
    Message::Hello {
        node_id: PEER_ID,
        domain: domain.into(),
        node: "peer".into(),
        namespace: String::new(),
        counter: 0,
        lease_ms: 5_000,
        gateway: false,
        asks_introduction,
    }
}

/// The safe sequence number of the next Hello the node sends the peer whose number is not in
/// `seen` (retransmissions of an unacknowledged introduction keep their number).
fn next_new_hello(peer: &Forger, node: SocketAddr, seen: &[u32], within: Duration) -> Option<u32> {
    peer.recv_numbered(node, within, |seq, m| {
        matches!(m, Message::Hello { .. }) && seq.is_some_and(|s| !seen.contains(&s))
    })
    .and_then(|(seq, _)| seq)
}

/// A runtime, a node in a domain of this test's own, its unicast address and a peer socket.
fn node_and_peer(test: &str) -> (tokio::runtime::Runtime, String, Node, SocketAddr, Forger) {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("a runtime");
    let domain = format!("{test}-{}", std::process::id());
    let node = rt.block_on(Node::open(&cfg(&domain))).expect("node opens");
    let at = unicast_of(&node);
    let peer = Forger::new(None).expect("a socket");
    (rt, domain, node, at, peer)
}

/// The peer's first Hello: the node registers it and introduces itself (a numbered Hello the
/// peer never acknowledges, so the node retransmits it under the same number): its number.
fn first_contact(
    rt: &tokio::runtime::Runtime,
    domain: &str,
    node: &Node,
    at: SocketAddr,
    peer: &mut Forger,
) -> u32 {
    peer.discovery(at, &hello(domain, false)).expect("send");
    let first = next_new_hello(peer, at, &[], Duration::from_secs(10))
        .expect("the node introduces itself to a new peer");
    assert!(
        rt.block_on(node.wait_until(Duration::from_secs(10), |n| {
            n.peers().iter().any(|p| p.name == "peer")
        })),
        "the node knows the peer"
    );
    first
}

/// The other side of the repair: a node hearing the heartbeat of a node it does not know
/// answers with its Hello, and that Hello says so.
#[test]
fn a_heartbeat_of_an_unknown_node_is_answered_by_a_hello_asking_for_its_introduction() {
    let (rt, domain, node, at, mut peer) = node_and_peer("discovery-ask");
    let heartbeat = Message::Heartbeat {
        node_id: PEER_ID,
        domain_hash: attacker::domain_hash(&domain),
        counter: 1,
    };
    peer.discovery(at, &heartbeat).expect("send");
    let answer = peer.recv_message(at, Duration::from_secs(10), |m| {
        matches!(m, Message::Hello { .. })
    });
    assert!(
        matches!(
            answer,
            Some(Message::Hello {
                asks_introduction: true,
                ..
            })
        ),
        "{answer:?}"
    );
    rt.block_on(node.shutdown());
}

#[test]
fn a_node_whose_introduction_was_lost_introduces_itself_again_when_asked() {
    let (rt, domain, node, at, mut peer) = node_and_peer("discovery-repair");

    // First contact: the node registers the peer and introduces itself, which the peer
    // "loses" (it never acknowledges; the node retransmits the same numbered Hello).
    let first = first_contact(&rt, &domain, &node, at, &mut peer);

    // Another plain Hello of a known peer (an introduction of its own) is no reason to
    // introduce ourselves again: two nodes would answer each other for ever.
    peer.discovery(at, &hello(&domain, false)).expect("send");
    assert_eq!(
        next_new_hello(&peer, at, &[first], Duration::from_secs(1)),
        None,
        "no second introduction for a plain Hello"
    );

    // The peer answers a heartbeat of the node's with its Hello, saying it does not know it:
    // the node introduces itself again (a new Hello, not a retransmission).
    peer.discovery(at, &hello(&domain, true)).expect("send");
    let again = next_new_hello(&peer, at, &[first], Duration::from_secs(10));
    assert!(
        again.is_some_and(|s| s > first),
        "introduced again after the peer said it does not know the node (first Hello #{first}, then {again:?})"
    );
    rt.block_on(node.shutdown());
}

/// A peer asks at every heartbeat it hears, and a forger may ask as often as it likes: the
/// node introduces itself again at most once per heartbeat period (5 s here), whatever the
/// number of asks (twenty in a burst: one new introduction, not twenty).
#[test]
fn asks_for_an_introduction_are_answered_at_most_once_per_heartbeat_period() {
    let (rt, domain, node, at, mut peer) = node_and_peer("discovery-limit");
    let first = first_contact(&rt, &domain, &node, at, &mut peer);
    for _ in 0..20 {
        peer.discovery(at, &hello(&domain, true)).expect("send");
    }
    let mut seen = vec![first];
    while let Some(s) = next_new_hello(&peer, at, &seen, Duration::from_millis(1500)) {
        seen.push(s);
    }
    assert_eq!(
        seen.len(),
        2,
        "one introduction, then one more for twenty asks: {seen:?}"
    );
    rt.block_on(node.shutdown());
}
