//! The Ethernet link: UDP multicast for discovery (Hello, Heartbeat, Bye), UDP unicast for data.
//! The sessions, the ARQ, the batching and the seal are the [`DatagramLink`]'s; this module is
//! the medium: the sockets, their options and their receive tasks.

use std::io;
use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4};
use std::sync::Arc;
use std::time::Duration;

use tokio::net::UdpSocket;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;

use super::arq::{ArqConfig, RetryLimit};
use super::auth::LinkSecurity;
use super::datagram::link::{DatagramLink, DatagramLinkOptions, Medium};
use super::{Link, LinkHandler, PeerAddr};

/// The UDP link: a [`DatagramLink`] over UDP sockets.
pub type UdpLink = DatagramLink<UdpMedium>;

/// How the UDP link is set up (taken from `<ethernet>` in network.xml).
#[derive(Debug, Clone)]
pub struct UdpLinkOptions {
    /// Link name.
    pub name: String,
    /// Unicast bind address (port 0 = any).
    pub bind: SocketAddr,
    /// Multicast group and port for discovery.
    pub multicast: SocketAddrV4,
    /// Interface address for multicast (127.0.0.1 keeps everything on this host).
    pub interface: Ipv4Addr,
    /// Multicast TTL.
    pub ttl: u32,
    /// Static unicast peers that also receive discovery messages.
    pub peers: Vec<SocketAddr>,
    /// Largest datagram built from several messages.
    pub mtu: usize,
    /// ARQ tuning.
    pub arq: ArqConfig,
    /// The domain key: when set, every datagram is sealed and only sealed ones are taken
    /// (see [`crate::link::auth`]).
    pub security: Option<LinkSecurity>,
}

/// Why the UDP link could not be opened.
#[derive(Debug, thiserror::Error)]
pub enum LinkOpenError {
    /// Binding the unicast socket failed.
    #[error("link {link}: cannot bind unicast socket {addr}: {source}")]
    Bind {
        /// Link name.
        link: String,
        /// The address.
        addr: SocketAddr,
        /// The OS error.
        source: io::Error,
    },
    /// Setting up the multicast socket failed.
    #[error("link {link}: cannot join multicast group {group} on interface {interface}: {source}")]
    Multicast {
        /// Link name.
        link: String,
        /// The group.
        group: SocketAddrV4,
        /// The interface.
        interface: Ipv4Addr,
        /// The OS error.
        source: io::Error,
    },
}

/// Largest datagram built for a peer on this host (a loopback address): loopback has no
/// link MTU to respect (64 KiB) and loses nothing to fragmentation, and every datagram costs
/// a system call and a wake-up at each end, so a fast stream to a local peer packs many more
/// messages into each (a 1 KiB event stream went from one event per datagram to 30 at 32 KiB,
/// and 60 KiB took ~12 % less subscriber CPU per 1 KiB event than 32 KiB).
const LOOPBACK_DATAGRAM: usize = 60 * 1024;

/// A receive buffer's capacity: the largest UDP payload (65,507 B), so no datagram is cut.
const RECEIVE_BUFFER: usize = 65_536;

/// UDP as a [`Medium`]: a unicast socket for data, the multicast group and the static peers
/// for discovery.
pub struct UdpMedium {
    /// The unicast socket as a plain non-blocking std socket, for sending: tokio's
    /// `try_send_to` refuses to send until its reactor has seen the socket writable, which
    /// lost the first Hello of every node.
    sender: std::net::UdpSocket,
    local: SocketAddr,
    multicast: SocketAddrV4,
    peers: Vec<SocketAddr>,
    mtu: usize,
}

impl Medium for UdpMedium {
    type Addr = SocketAddr;

    fn peer_addr(addr: SocketAddr) -> PeerAddr {
        PeerAddr::Udp(addr)
    }

    fn medium_addr(to: PeerAddr) -> Option<SocketAddr> {
        match to {
            PeerAddr::Udp(a) => Some(a),
            _ => None,
        }
    }

    fn send_to(&self, d: &[u8], to: SocketAddr) -> io::Result<()> {
        self.sender.send_to(d, to).map(drop)
    }

    fn announce_targets(&self) -> usize {
        1 + self.peers.len()
    }

    fn announce_to(&self, d: &[u8], target: usize) -> io::Result<()> {
        let to = match target {
            0 => SocketAddr::V4(self.multicast),
            i => self.peers[i - 1],
        };
        self.sender.send_to(d, to).map(drop)
    }

    /// See [`LOOPBACK_DATAGRAM`].
    fn datagram_max(&self, to: SocketAddr) -> usize {
        if to.ip().is_loopback() {
            self.mtu.max(LOOPBACK_DATAGRAM)
        } else {
            self.mtu
        }
    }

    fn local_addr(&self) -> String {
        format!("udp://{}", self.local)
    }
}

impl DatagramLink<UdpMedium> {
    /// Opens the sockets and starts the receive and transmit tasks on `tasks`, stopping on
    /// `cancel`.
    ///
    /// # Errors
    /// [`LinkOpenError`] when a socket cannot be bound or the group joined.
    pub fn open(
        index: usize,
        options: UdpLinkOptions,
        handler: Arc<dyn LinkHandler>,
        tasks: &TaskTracker,
        cancel: CancellationToken,
    ) -> Result<Arc<Self>, LinkOpenError> {
        let bind_err = |source| LinkOpenError::Bind {
            link: options.name.clone(),
            addr: options.bind,
            source,
        };
        let mcast_err = |source| LinkOpenError::Multicast {
            link: options.name.clone(),
            group: options.multicast,
            interface: options.interface,
            source,
        };
        let data = std::net::UdpSocket::bind(options.bind).map_err(bind_err)?;
        data.set_nonblocking(true).map_err(bind_err)?;
        let data2 = socket2::Socket::from(data);
        // Bigger buffers absorb bursts of a batching sender; the OS may cap them.
        let _ = data2.set_recv_buffer_size(4 << 20);
        let _ = data2.set_send_buffer_size(4 << 20);
        data2
            .set_multicast_if_v4(&options.interface)
            .map_err(mcast_err)?;
        data2.set_multicast_loop_v4(true).map_err(mcast_err)?;
        data2.set_multicast_ttl_v4(options.ttl).map_err(mcast_err)?;
        let data: std::net::UdpSocket = data2.into();
        let sender = data.try_clone().map_err(bind_err)?;
        let socket = UdpSocket::from_std(data).map_err(bind_err)?;
        let mut local = socket.local_addr().map_err(bind_err)?;
        if local.ip().is_unspecified() && !options.interface.is_unspecified() {
            local.set_ip(options.interface.into());
        }

        let mcast = {
            use socket2::{Domain, Protocol, Socket, Type};
            let s =
                Socket::new(Domain::IPV4, Type::DGRAM, Some(Protocol::UDP)).map_err(mcast_err)?;
            s.set_reuse_address(true).map_err(mcast_err)?;
            s.bind(&SocketAddr::V4(options.multicast).into())
                .map_err(mcast_err)?;
            s.join_multicast_v4(options.multicast.ip(), &options.interface)
                .map_err(mcast_err)?;
            s.set_nonblocking(true).map_err(mcast_err)?;
            UdpSocket::from_std(s.into()).map_err(mcast_err)?
        };

        let medium = UdpMedium {
            sender,
            local,
            multicast: options.multicast,
            peers: options.peers,
            mtu: options.mtu,
        };
        let link = DatagramLink::create(
            index,
            DatagramLinkOptions {
                name: options.name,
                arq: options.arq,
                retry_limit: RetryLimit::lan(),
                security: options.security,
            },
            medium,
            handler,
            tasks,
            cancel.clone(),
        );
        let l = link.clone();
        let c = cancel.clone();
        crate::sync::spawn_tracked(tasks, async move { receive_loop(l, socket, c).await });
        let l = link.clone();
        crate::sync::spawn_tracked(tasks, async move { multicast_loop(l, mcast, cancel).await });
        Ok(link)
    }

    /// The unicast address peers reach this link at.
    pub fn local_socket_addr(&self) -> SocketAddr {
        self.medium().local
    }
}

async fn receive_loop(link: Arc<UdpLink>, socket: UdpSocket, cancel: CancellationToken) {
    // Received into the spare capacity and never zero-filled, so only the pages datagrams
    // actually reach become resident: an idle node's two receive buffers cost a few KiB
    // instead of 128.
    let mut buf = Vec::with_capacity(RECEIVE_BUFFER);
    loop {
        buf.clear();
        let r = tokio::select! {
            _ = cancel.cancelled() => break,
            r = socket.recv_buf_from(&mut buf) => r,
        };
        match r {
            Ok((n, from)) => {
                let mut touched = Vec::new();
                link.receive(&mut buf[..n], from, &mut touched);
                // Drain what else is waiting so acknowledgements are batched. In such a
                // burst, let the tasks the previous datagram woke on this worker run first:
                // a subscriber would otherwise wait for the whole drain and find most of
                // its variables' values replaced by newer ones. (A lone datagram yields
                // nothing: the woken task runs as soon as this loop waits again, which
                // keeps the round trip short.)
                for _ in 0..64 {
                    buf.clear();
                    match socket.try_recv_buf_from(&mut buf) {
                        Ok((n, from)) => {
                            tokio::task::yield_now().await;
                            link.receive(&mut buf[..n], from, &mut touched);
                        }
                        Err(_) => break,
                    }
                }
                link.received(touched);
            }
            Err(e) if is_transient(&e) => continue,
            Err(e) => {
                tracing::warn!(link = %link.name(), error = %e, "receive failed");
                tokio::select! {
                    _ = cancel.cancelled() => break,
                    _ = tokio::time::sleep(Duration::from_millis(100)) => {}
                }
            }
        }
    }
}

async fn multicast_loop(link: Arc<UdpLink>, sock: UdpSocket, cancel: CancellationToken) {
    let mut buf = Vec::with_capacity(RECEIVE_BUFFER);
    loop {
        buf.clear();
        let r = tokio::select! {
            _ = cancel.cancelled() => break,
            r = sock.recv_buf_from(&mut buf) => r,
        };
        match r {
            Ok((n, from)) => link.receive_announce(&mut buf[..n], from),
            Err(e) if is_transient(&e) => continue,
            Err(e) => {
                tracing::warn!(link = %link.name(), error = %e, "multicast receive failed");
                tokio::select! {
                    _ = cancel.cancelled() => break,
                    _ = tokio::time::sleep(Duration::from_millis(100)) => {}
                }
            }
        }
    }
}

fn is_transient(e: &io::Error) -> bool {
    // ICMP port unreachable from a vanished peer surfaces as ConnectionRefused on Linux.
    matches!(
        e.kind(),
        io::ErrorKind::ConnectionRefused
            | io::ErrorKind::ConnectionReset
            | io::ErrorKind::Interrupted
    )
}
