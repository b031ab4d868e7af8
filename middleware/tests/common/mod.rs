//! What the middleware's in-process tests share (each test file uses what it needs).
#![allow(dead_code)]

use std::net::{Ipv4Addr, SocketAddrV4};
use std::time::Duration;

use marea::config::{EthernetConfig, LinkConfig};
use marea::NetworkConfig;

/// A node `node` of `domain` on loopback, discovering peers on multicast group
/// `239.255.77.<group>:port` (each test file its own group), with 200 ms heartbeats and the
/// given lease.
pub fn loopback_config(
    node: &str,
    domain: &str,
    group: u8,
    port: u16,
    lease: Duration,
) -> NetworkConfig {
    let mut c = NetworkConfig::ethernet_loopback(node);
    c.domain = domain.into();
    c.links = vec![LinkConfig::Ethernet(EthernetConfig {
        interface: Ipv4Addr::LOCALHOST,
        bind: "127.0.0.1:0".parse().expect("literal address"),
        multicast: SocketAddrV4::new(Ipv4Addr::new(239, 255, 77, group), port),
        heartbeat: Duration::from_millis(200),
        lease,
        ..EthernetConfig::default()
    })];
    c
}

/// Options of a UDP link on loopback for the link-level tests, named `name`, discovering on
/// multicast group `239.255.77.<group>:port` (each test file its own group); MTU 1,400 for
/// every peer but loopback ones (loopback datagrams are up to 60 KiB).
pub fn udp_link_options(name: &str, group: u8, port: u16) -> marea::link::udp::UdpLinkOptions {
    marea::link::udp::UdpLinkOptions {
        name: name.into(),
        bind: "127.0.0.1:0".parse().expect("a literal address"),
        multicast: SocketAddrV4::new(Ipv4Addr::new(239, 255, 77, group), port),
        interface: Ipv4Addr::LOCALHOST,
        ttl: 0,
        peers: vec![],
        mtu: 1400,
        arq: marea::link::arq::ArqConfig::lan(),
        security: None,
    }
}
