//! What the middleware's in-process tests share.

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
