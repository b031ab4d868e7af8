//! An attacker without the domain key, on the same LAN (loopback here): it forges discovery
//! and session datagrams with real UDP sockets. Shared by `tests/hostile_flood.rs` and
//! `benches/security/hostile.rs` (included by path).

#![allow(dead_code)]

use std::io;
use std::net::{SocketAddr, UdpSocket};
use std::time::{Duration, Instant};

use marea::codec::encode_message;
use marea::link::datagram::{discovery_datagram, DatagramWriter};
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
        asks_introduction: false,
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

/// A node of `domain` with one Ethernet link on loopback, announcing on `group`, heartbeat
/// every 200 ms: the victim an attacker (or a forged peer) talks to.
pub fn loopback_node_config(
    node: &str,
    domain: &str,
    group: std::net::SocketAddrV4,
    lease: Duration,
) -> marea::NetworkConfig {
    let mut c = marea::NetworkConfig::ethernet_loopback(node);
    c.domain = domain.into();
    c.links = vec![marea::config::LinkConfig::Ethernet(
        marea::config::EthernetConfig {
            interface: std::net::Ipv4Addr::LOCALHOST,
            bind: "127.0.0.1:0".parse().expect("a literal address"),
            multicast: group,
            heartbeat: Duration::from_millis(200),
            lease,
            ..marea::config::EthernetConfig::default()
        },
    )];
    c
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

/// A hand-made node on a UDP socket of its own: it says what it likes, sealed with a domain key
/// when it has one (an insider of another namespace) or in clear (an outsider). Counts the
/// datagrams it sent.
pub struct Forger {
    sock: UdpSocket,
    sealer: Option<marea::link::auth::Sealer>,
    seq: u32,
    /// Datagrams sent so far.
    pub sent: u64,
    /// Sends from this address instead of its socket's (a forged source address).
    spoof: Option<(Spoofer, std::net::SocketAddrV4)>,
}

impl Forger {
    /// A forger on a fresh loopback socket, sealing with `key` when given.
    pub fn new(key: Option<&marea::link::auth::DomainKey>) -> io::Result<Forger> {
        let sock = UdpSocket::bind("127.0.0.1:0")?;
        sock.set_read_timeout(Some(Duration::from_millis(50)))?;
        Ok(Forger {
            sock,
            sealer: key.map(|k| marea::link::auth::Sealer::new(k, marea::link::auth::Profile::UDP)),
            seq: 0,
            sent: 0,
            spoof: None,
        })
    }

    /// A forger whose datagrams carry source address `from` (another node's); `None` without
    /// the privilege of raw sockets.
    pub fn spoofing(
        key: Option<&marea::link::auth::DomainKey>,
        from: std::net::SocketAddrV4,
    ) -> Option<Forger> {
        let mut f = Forger::new(key).ok()?;
        f.spoof = Some((Spoofer::open()?, from));
        Some(f)
    }

    /// Its source address.
    pub fn addr(&self) -> SocketAddr {
        self.sock
            .local_addr()
            .expect("a bound socket has an address")
    }

    /// Sends datagram `d` (built by `marea::link::datagram`), sealed if it has a key.
    pub fn send(&mut self, to: SocketAddr, mut d: Vec<u8>) -> io::Result<()> {
        if let (Some(s), Some(kind)) = (&self.sealer, d.first_mut()) {
            *kind = marea::link::datagram::sealed_kind(*kind);
            s.seal(&mut d, usize::MAX);
        }
        self.raw(to, &d)
    }

    /// Sends `d` exactly as given (a replay).
    pub fn raw(&mut self, to: SocketAddr, d: &[u8]) -> io::Result<()> {
        match (&self.spoof, to) {
            (Some((s, from)), SocketAddr::V4(to)) => s.send(*from, to, d)?,
            _ => {
                self.sock.send_to(d, to)?;
            }
        }
        self.sent += 1;
        Ok(())
    }

    /// A discovery message (Hello, Heartbeat, Bye).
    pub fn discovery(&mut self, to: SocketAddr, msg: &Message) -> io::Result<()> {
        self.send(to, discovery_datagram(&encode_message(msg)))
    }

    /// Safe messages in a session of its own (opened by a SYN before the first), one
    /// datagram per message.
    pub fn safe(&mut self, to: SocketAddr, msgs: &[Message]) -> io::Result<()> {
        for m in msgs {
            let mut w = DatagramWriter::new(65_000);
            if self.seq == 0 {
                w.push_syn(0x5eed);
            }
            if !w.push_safe(self.seq, &encode_message(m)) {
                return Err(io::Error::other("a safe message larger than a datagram"));
            }
            self.seq += 1;
            self.send(to, w.take())?;
        }
        Ok(())
    }

    /// A fast (best-effort) message.
    pub fn fast(&mut self, to: SocketAddr, msg: &Message) -> io::Result<()> {
        let mut w = DatagramWriter::new(65_000);
        if !w.push_fast(&encode_message(msg)) {
            return Err(io::Error::other("a fast message larger than a datagram"));
        }
        self.send(to, w.take())
    }
}

impl Forger {
    /// Waits (at most `within`) for a message from `from` satisfying `pred`, reading the
    /// datagrams sent to this forger (sealed or not: a seal is a trailer, and this forger is
    /// not the one checking it).
    pub fn recv_message(
        &self,
        from: SocketAddr,
        within: Duration,
        pred: impl Fn(&Message) -> bool,
    ) -> Option<Message> {
        self.recv_numbered(from, within, |_, m| pred(m))
            .map(|(_, m)| m)
    }

    /// [`Self::recv_message`] with each message's safe sequence number (`None` for a fast or
    /// discovery one): a retransmission has the number of the first copy.
    pub fn recv_numbered(
        &self,
        from: SocketAddr,
        within: Duration,
        pred: impl Fn(Option<u32>, &Message) -> bool,
    ) -> Option<(Option<u32>, Message)> {
        use marea::link::datagram::{self, Datagram, Entry};
        let deadline = Instant::now() + within;
        let trailer = marea::link::auth::Profile::UDP.overhead();
        let mut buf = vec![0u8; 65_536];
        while Instant::now() < deadline {
            let Ok((n, src)) = self.sock.recv_from(&mut buf) else {
                continue;
            };
            if src != from || n == 0 {
                continue;
            }
            let mut d = buf[..n].to_vec();
            if let Some(kind) = datagram::unsealed_kind(d[0]) {
                if d.len() <= trailer {
                    continue;
                }
                d.truncate(d.len() - trailer);
                d[0] = kind;
            }
            let msgs: Vec<(Option<u32>, Vec<u8>)> = match datagram::decode(&d) {
                Ok(Datagram::Discovery(m)) => vec![(None, m.to_vec())],
                Ok(Datagram::Data(entries)) => entries
                    .into_iter()
                    .filter_map(|e| match e {
                        Entry::Safe { seq, msg } => Some((Some(seq), msg.to_vec())),
                        Entry::Fast(msg) => Some((None, msg.to_vec())),
                        _ => None,
                    })
                    .collect(),
                Err(_) => vec![],
            };
            for (seq, m) in msgs {
                if let Ok(m) = marea::codec::decode_message(&m) {
                    if pred(seq, &m) {
                        return Some((seq, m));
                    }
                }
            }
        }
        None
    }
}

/// A listener on a domain's multicast group, as anyone on the LAN can open: it captures the
/// sealed discovery datagrams the nodes announce (to replay them) and reads their node ids (a
/// seal authenticates, it does not hide).
pub struct Sniffer {
    sock: UdpSocket,
}

impl Sniffer {
    /// Joins `group` on the loopback interface.
    pub fn join(group: std::net::SocketAddrV4) -> io::Result<Sniffer> {
        use socket2::{Domain, Protocol, Socket, Type};
        let s = Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP))?;
        s.set_reuse_address(true)?;
        s.bind(&SocketAddr::V4(group).into())?;
        s.join_multicast_v4(group.ip(), &std::net::Ipv4Addr::LOCALHOST)?;
        let sock: UdpSocket = s.into();
        sock.set_read_timeout(Some(Duration::from_millis(100)))?;
        Ok(Sniffer { sock })
    }

    /// One datagram heard on the group (waiting at most 100 ms) and who sent it.
    pub fn recv(&self) -> Option<(Vec<u8>, SocketAddr)> {
        let mut buf = vec![0u8; 65_536];
        let (n, from) = self.sock.recv_from(&mut buf).ok()?;
        buf.truncate(n);
        Some((buf, from))
    }

    /// Sends `d` to `to` from the listener's socket (a replay).
    pub fn send_to(&self, d: &[u8], to: SocketAddr) -> io::Result<()> {
        self.sock.send_to(d, to).map(|_| ())
    }

    /// Waits (at most `within`) for a sealed discovery datagram from `from`: its node id and
    /// the datagram as it was on the wire.
    pub fn capture_from(&self, from: SocketAddr, within: Duration) -> Option<(NodeId, Vec<u8>)> {
        let deadline = Instant::now() + within;
        let mut buf = vec![0u8; 65_536];
        while Instant::now() < deadline {
            let Ok((n, src)) = self.sock.recv_from(&mut buf) else {
                continue;
            };
            if src != from {
                continue;
            }
            if let Some(id) = sealed_discovery_sender(&buf[..n]) {
                return Some((id, buf[..n].to_vec()));
            }
        }
        None
    }
}

/// The node id in a sealed Hello or Heartbeat, read without the key: the seal is a trailer.
fn sealed_discovery_sender(d: &[u8]) -> Option<NodeId> {
    use marea::link::datagram::{self, Datagram, KIND_DISCOVERY, KIND_SEALED_DISCOVERY};
    let trailer = marea::link::auth::Profile::UDP.overhead();
    if d.first() != Some(&KIND_SEALED_DISCOVERY) || d.len() <= 1 + trailer {
        return None;
    }
    let mut plain = d[..d.len() - trailer].to_vec();
    plain[0] = KIND_DISCOVERY;
    let Ok(Datagram::Discovery(m)) = datagram::decode(&plain) else {
        return None;
    };
    match marea::codec::decode_message(m) {
        Ok(Message::Heartbeat { node_id, .. }) | Ok(Message::Hello { node_id, .. }) => {
            Some(node_id)
        }
        _ => None,
    }
}

/// A sender of UDP datagrams with any source address, as anyone on a LAN can forge one: a raw
/// IP socket (root, or `CAP_NET_RAW`).
pub struct Spoofer(socket2::Socket);

impl Spoofer {
    /// The raw socket; `None` without the privilege (the caller says so: see
    /// `test_support::tool_missing`).
    pub fn open() -> Option<Spoofer> {
        use socket2::{Domain, Protocol, Socket, Type};
        Socket::new(
            Domain::IPV4,
            Type::RAW,
            Some(Protocol::from(libc::IPPROTO_RAW)),
        )
        .ok()
        .map(Spoofer)
    }

    /// Sends UDP `payload` to `to` as if from `from`.
    pub fn send(
        &self,
        from: std::net::SocketAddrV4,
        to: std::net::SocketAddrV4,
        payload: &[u8],
    ) -> io::Result<()> {
        let udp_len = 8 + payload.len();
        let total = 20 + udp_len;
        let mut p = Vec::with_capacity(total);
        p.extend_from_slice(&[0x45, 0]);
        p.extend_from_slice(&(total as u16).to_be_bytes());
        // Id, flags (don't fragment), TTL, UDP, checksum (below).
        p.extend_from_slice(&[0, 0, 0x40, 0, 64, 17, 0, 0]);
        p.extend_from_slice(&from.ip().octets());
        p.extend_from_slice(&to.ip().octets());
        let sum = ipv4_checksum(&p);
        p[10..12].copy_from_slice(&sum.to_be_bytes());
        p.extend_from_slice(&from.port().to_be_bytes());
        p.extend_from_slice(&to.port().to_be_bytes());
        p.extend_from_slice(&(udp_len as u16).to_be_bytes());
        // No UDP checksum (allowed over IPv4).
        p.extend_from_slice(&[0, 0]);
        p.extend_from_slice(payload);
        self.0.send_to(&p, &SocketAddr::V4(to).into()).map(|_| ())
    }
}

/// The Internet checksum of an IPv4 header.
fn ipv4_checksum(header: &[u8]) -> u16 {
    let mut sum: u32 = header
        .chunks(2)
        .map(|c| u32::from(u16::from_be_bytes([c[0], *c.get(1).unwrap_or(&0)])))
        .sum();
    while sum > 0xffff {
        sum = (sum & 0xffff) + (sum >> 16);
    }
    !(sum as u16)
}

/// A listener to every IP packet on the loopback interface (a packet socket: root, or
/// `CAP_NET_RAW`), as anyone on a LAN's segment can read the datagrams two nodes exchange.
pub struct LoopbackCapture(std::os::fd::OwnedFd);

impl LoopbackCapture {
    /// The packet socket on `lo`; `None` without the privilege.
    #[allow(unsafe_code)]
    pub fn open() -> Option<LoopbackCapture> {
        use std::os::fd::{FromRawFd, OwnedFd};
        let proto = (libc::ETH_P_IP as u16).to_be();
        // SAFETY: plain socket(2); the descriptor is owned below.
        let fd = unsafe {
            libc::socket(
                libc::AF_PACKET,
                libc::SOCK_DGRAM | libc::SOCK_CLOEXEC,
                i32::from(proto),
            )
        };
        if fd < 0 {
            return None;
        }
        // SAFETY: `fd` is a fresh descriptor nothing else owns.
        let owned = unsafe { OwnedFd::from_raw_fd(fd) };
        // SAFETY: a NUL-terminated name.
        let lo = unsafe { libc::if_nametoindex(c"lo".as_ptr()) };
        // SAFETY: sockaddr_ll is plain data; zeroed is a valid value.
        let mut addr: libc::sockaddr_ll = unsafe { std::mem::zeroed() };
        addr.sll_family = libc::AF_PACKET as u16;
        addr.sll_protocol = proto;
        addr.sll_ifindex = lo as i32;
        // SAFETY: `addr` is a sockaddr_ll of the size given.
        let bound = unsafe {
            libc::bind(
                fd,
                std::ptr::addr_of!(addr).cast(),
                std::mem::size_of::<libc::sockaddr_ll>() as u32,
            )
        };
        let timeout = libc::timeval {
            tv_sec: 0,
            tv_usec: 50_000,
        };
        // SAFETY: a timeval of the size given.
        let timed = unsafe {
            libc::setsockopt(
                fd,
                libc::SOL_SOCKET,
                libc::SO_RCVTIMEO,
                std::ptr::addr_of!(timeout).cast(),
                std::mem::size_of::<libc::timeval>() as u32,
            )
        };
        (bound == 0 && timed == 0).then_some(LoopbackCapture(owned))
    }

    /// The payloads of up to `n` UDP datagrams from `from` to `to` seen within `within`.
    #[allow(unsafe_code)]
    pub fn udp(
        &self,
        from: std::net::SocketAddrV4,
        to: std::net::SocketAddrV4,
        n: usize,
        within: Duration,
    ) -> Vec<Vec<u8>> {
        use std::os::fd::AsRawFd;
        let deadline = Instant::now() + within;
        let mut buf = vec![0u8; 70_000];
        let mut got = Vec::new();
        while got.len() < n && Instant::now() < deadline {
            // SAFETY: reads at most `buf.len()` bytes into `buf`.
            let len =
                unsafe { libc::recv(self.0.as_raw_fd(), buf.as_mut_ptr().cast(), buf.len(), 0) };
            let Ok(len) = usize::try_from(len) else {
                continue;
            };
            let p = &buf[..len];
            if p.len() < 28 || p[0] >> 4 != 4 || p[9] != 17 {
                continue;
            }
            let ihl = usize::from(p[0] & 0x0f) * 4;
            if p.len() < ihl + 8 {
                continue;
            }
            let ip = |o: usize| std::net::Ipv4Addr::new(p[o], p[o + 1], p[o + 2], p[o + 3]);
            let port = |o: usize| u16::from_be_bytes([p[o], p[o + 1]]);
            let (src, dst) = (
                std::net::SocketAddrV4::new(ip(12), port(ihl)),
                std::net::SocketAddrV4::new(ip(16), port(ihl + 2)),
            );
            if src == from && dst == to {
                got.push(p[ihl + 8..].to_vec());
            }
        }
        got
    }
}
