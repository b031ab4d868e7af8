//! An attacker without the domain key, on the same LAN (loopback here): it forges discovery
//! and session datagrams with real UDP sockets. Shared by `tests/hostile_flood.rs` and
//! `benches/security/hostile.rs` (included by path).

#![allow(dead_code)]

use std::io;
use std::net::{SocketAddr, UdpSocket};
use std::time::{Duration, Instant};

use marea::codec::encode_message;
use marea::link::udp::datagram::{discovery_datagram, DatagramWriter};
use marea::protocol::{Declaration, ItemKind, LoggedDeclaration, Message, NodeId};
use marea::typeinfo::TypeInfo;

/// The domain hash heartbeats carry, as anyone who hears one heartbeat of the domain reads it
/// off the wire (the first four bytes of the BLAKE3 hash of the domain name, little-endian).
pub fn domain_hash(domain: &str) -> u32 {
    let h = blake3::hash(domain.as_bytes());
    let b = h.as_bytes();
    u32::from_le_bytes([b[0], b[1], b[2], b[3]])
}

/// A heartbeat datagram of an invented node.
pub fn heartbeat(node_id: NodeId, domain_hash: u32) -> Vec<u8> {
    discovery_datagram(&encode_message(&Message::Heartbeat {
        node_id,
        domain_hash,
        counter: 1,
    }))
}

/// A Hello datagram of an invented node asking for `lease_ms`.
pub fn hello(node_id: NodeId, domain: &str, name: &str, lease_ms: u32) -> Vec<u8> {
    discovery_datagram(&encode_message(&Message::Hello {
        node_id,
        domain: domain.to_owned(),
        node: name.to_owned(),
        namespace: String::new(),
        counter: 1,
        lease_ms,
        gateway: false,
    }))
}

/// A session datagram opening session `session` with one safe message: a declaration batch
/// whose only entry is an interest in `pattern`.
pub fn interest_batch(session: u32, pattern: &str) -> Vec<u8> {
    let msg = encode_message(&Message::DeclBatch {
        after: 0,
        upto: 1,
        reset: false,
        entries: vec![LoggedDeclaration {
            counter: 1,
            decl: Declaration::Interest {
                id: 1,
                service: 1,
                kind: ItemKind::Event,
                pattern: pattern.to_owned(),
                ty: TypeInfo::of::<u8>(),
            },
        }],
    });
    let mut w = DatagramWriter::new(65_000);
    assert!(
        w.push_syn(session) && w.push_safe(0, &msg),
        "fits one datagram"
    );
    w.take()
}

/// The unicast address of a node's first link (`udp://host:port`).
pub fn unicast_of(node: &marea::Node) -> SocketAddr {
    let a = node.link_addrs().into_iter().next().expect("a link");
    a.trim_start_matches("udp://")
        .parse()
        .expect("a UDP address")
}

/// Sends `count` heartbeats of distinct invented node ids to `target`, each from its own
/// socket (so from its own source port: `batch` sockets are open at once, each on a port the
/// kernel picked, and closed before the next batch). `after_batch` is told how many were sent
/// so far after each batch (to pace the flood to what the victim reads, so the kernel does not
/// drop it). Returns how many were sent.
///
/// # Errors
/// The first socket error.
pub fn flood_heartbeats(
    target: SocketAddr,
    domain: &str,
    count: usize,
    batch: usize,
    first_id: NodeId,
    mut after_batch: impl FnMut(usize),
) -> io::Result<usize> {
    let hash = domain_hash(domain);
    let mut sent = 0;
    while sent < count {
        let n = batch.min(count - sent);
        let mut open = Vec::with_capacity(n);
        for _ in 0..n {
            let s = UdpSocket::bind("127.0.0.1:0")?;
            s.send_to(&heartbeat(first_id + sent as NodeId, hash), target)?;
            open.push(s);
            sent += 1;
        }
        after_batch(sent);
    }
    Ok(sent)
}

/// Waits (polling, at most `within`) until `node`'s first link has received `frames` frames
/// in all: counters have no change signal, and a flood paced on them is not dropped by the
/// kernel's receive buffer.
pub fn wait_frames_in(node: &marea::Node, frames: u64, within: Duration) -> bool {
    let deadline = Instant::now() + within;
    loop {
        let got = node.link_stats().first().map_or(0, |(_, s)| s.frames_in);
        if got >= frames {
            return true;
        }
        if Instant::now() >= deadline {
            return false;
        }
        std::thread::sleep(Duration::from_millis(2));
    }
}
