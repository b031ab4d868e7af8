//! The typed configuration of one node: [`NetworkConfig`] and one struct per link kind, with the
//! defaults a `network.xml` falls back on.

use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4};
use std::path::PathBuf;
use std::time::Duration;

use super::values::*;
pub use crate::link::{ShmWait, ZenohMode};

/// One node's network configuration: who it is and which links it uses.
#[derive(Debug, Clone, PartialEq)]
pub struct NetworkConfig {
    /// This node's name (`node` attribute), `[A-Za-z0-9_-]+`.
    pub node: String,
    /// Prefix for this node's services' items (`rover1` gives `rover1/vas/position`); may be
    /// hierarchical (`fleet/rover1`). `None` when the attribute is absent.
    pub namespace: Option<String>,
    /// Isolation key: nodes of different domains ignore each other. Defaults to
    /// [`DEFAULT_DOMAIN`](super::DEFAULT_DOMAIN).
    pub domain: String,
    /// The enabled links, in file order. Links with `enabled="false"` are left out.
    pub links: Vec<LinkConfig>,
    /// Whether the node forwards between its links (`gateway` attribute). `None` (the
    /// default) forwards when a serial link sits beside another link: the radio gateway.
    pub gateway: Option<bool>,
    /// The file this configuration was read from, if any.
    pub source: Option<PathBuf>,
    /// The `<access>` rules; `None` (no element) leaves everything open.
    pub access: Option<super::access::AccessConfig>,
    /// Link authentication (`<security>`): `None` keeps the links open to anyone (the
    /// zero-config demo).
    pub security: Option<SecurityConfig>,
}

/// `<security keyFile="..." encrypt="radio"/>`: the domain key every link seals its frames
/// with (see [`crate::link::auth`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SecurityConfig {
    /// The key file (`keyFile`), made by `usal keygen`; a relative path in the file is taken
    /// relative to the file's directory.
    pub key_file: PathBuf,
    /// Whether serial (radio) links also encrypt their data (`encrypt="radio"`; default
    /// `none`: authenticated only).
    pub encrypt_radio: bool,
    /// This node's identity key (`identityFile`, made by `usal keygen --identity`): the node
    /// proves it to its peers after each Hello.
    pub identity_file: Option<PathBuf>,
    /// The domain's roster (`identities`, an `identities.xml`): which identity key may own
    /// which namespaces. With it, a peer's declarations are taken only once its key is
    /// authenticated for its namespace.
    pub identities: Option<PathBuf>,
}

/// One link of a node, by medium.
#[derive(Debug, Clone, PartialEq)]
pub enum LinkConfig {
    /// UDP over Ethernet/IP: multicast discovery plus unicast data.
    Ethernet(EthernetConfig),
    /// Same-host shared memory (iceoryx2).
    Shm(ShmConfig),
    /// Serial Transport Protocol over one bidirectional serial port.
    Serial(SerialConfig),
    /// Serial Transport Protocol over two one-way ports (one for Tx, one for Rx).
    SerialDuo(SerialDuoConfig),
    /// marea's datagrams through an Eclipse Zenoh session: beyond one LAN, through routers.
    Zenoh(ZenohConfig),
}

impl LinkConfig {
    /// The link's name, unique within a node (`ethernet0`, `radio`...).
    pub fn name(&self) -> &str {
        match self {
            LinkConfig::Ethernet(c) => &c.name,
            LinkConfig::Shm(c) => &c.name,
            LinkConfig::Serial(c) => &c.name,
            LinkConfig::SerialDuo(c) => &c.name,
            LinkConfig::Zenoh(c) => &c.name,
        }
    }
}

/// An `<ethernet>` link: UDP unicast for data, UDP multicast for discovery.
#[derive(Debug, Clone, PartialEq)]
pub struct EthernetConfig {
    /// Link name (`name`), default `ethernet<index>`.
    pub name: String,
    /// Local unicast socket address (`bind`), default `0.0.0.0:0` (any address, any port).
    pub bind: SocketAddr,
    /// Discovery multicast group and port (`multicast`), default `239.255.77.1:7477`.
    pub multicast: SocketAddrV4,
    /// Interface to join the multicast group on (`interface`), default `0.0.0.0`.
    pub interface: Ipv4Addr,
    /// Heartbeat period (`heartbeatMs`), default 1000 ms.
    pub heartbeat: Duration,
    /// A peer silent this long is gone (`leaseMs`), default 3.5 × heartbeat.
    pub lease: Duration,
    /// Multicast time-to-live (`ttl`), default 1 (stay on the local subnet).
    pub ttl: u32,
    /// Static unicast peers (`<peer address="..."/>`) for networks without multicast.
    pub peers: Vec<SocketAddr>,
}

impl Default for EthernetConfig {
    fn default() -> Self {
        Self {
            name: "ethernet0".to_owned(),
            bind: SocketAddr::from(([0, 0, 0, 0], 0)),
            multicast: SocketAddrV4::new(Ipv4Addr::new(239, 255, 77, 1), 7477),
            interface: Ipv4Addr::UNSPECIFIED,
            heartbeat: Duration::from_millis(ETHERNET_HEARTBEAT_MS),
            lease: Duration::from_millis(lease_ms(ETHERNET_HEARTBEAT_MS, ETHERNET_LEASE)),
            ttl: 1,
            peers: Vec::new(),
        }
    }
}

/// A `<zenoh>` link: the node's datagrams carried by an Eclipse Zenoh session, to the nodes of
/// its domain that share no LAN with it (a ground station in another building, a cloud
/// machine), through Zenoh routers over TCP, TLS or QUIC.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct ZenohConfig {
    /// Link name (`name`), default `zenoh<index>`.
    pub name: String,
    /// How the session joins (`mode`), default `client`.
    pub mode: ZenohMode,
    /// Endpoints to connect to (`connect`, comma-separated), e.g. `tcp/10.0.0.1:7447`.
    pub connect: Vec<String>,
    /// Endpoints to listen on (`listen`, comma-separated; peers only).
    pub listen: Vec<String>,
    /// A Zenoh configuration file (`config`, JSON5; relative to the network file) for
    /// everything else: TLS certificates, user and password, timeouts. `mode`, `connect` and
    /// `listen` given as attributes override it.
    pub config_file: Option<std::path::PathBuf>,
    /// Heartbeat period (`heartbeatMs`), default 1000 ms.
    pub heartbeat: Duration,
    /// A peer silent this long is gone (`leaseMs`), default 60 × heartbeat: a router restart
    /// or a WAN outage of half a minute loses nothing.
    pub lease: Duration,
}

/// A `<shm>` link: same-host shared memory through iceoryx2.
#[derive(Debug, Clone, PartialEq)]
pub struct ShmConfig {
    /// Link name (`name`), default `shm<index>`.
    pub name: String,
    /// iceoryx2 service-name prefix (`service`), default `usal`.
    pub service: String,
    /// Heartbeat period (`heartbeatMs`), default 1000 ms.
    pub heartbeat: Duration,
    /// A peer silent this long is gone (`leaseMs`), default 3.5 × heartbeat.
    pub lease: Duration,
    /// How the link waits for messages (`wait`: `event`, the default, sleeps until a writer
    /// wakes it; `spin` busy-polls from a task of the link, yielding its tokio worker between
    /// polls, so writers never make a system call).
    pub wait: ShmWait,
    /// Most same-host peers (other links of the same `service`) this link's inbox admits
    /// (`maxPeers`), default 16. Each costs ~11 KiB of memory whether or not it comes; a peer
    /// beyond it cannot reach this node over shared memory (both sides log it).
    pub max_peers: usize,
}

impl Default for ShmConfig {
    fn default() -> Self {
        Self {
            name: "shm0".to_owned(),
            service: "usal".to_owned(),
            heartbeat: Duration::from_millis(SHM_HEARTBEAT_MS),
            lease: Duration::from_millis(lease_ms(SHM_HEARTBEAT_MS, SHM_LEASE)),
            wait: ShmWait::Event,
            max_peers: SHM_MAX_PEERS as usize,
        }
    }
}

/// A `<serial>` link: the Serial Transport Protocol over one bidirectional port.
#[derive(Debug, Clone, PartialEq)]
pub struct SerialConfig {
    /// Link name (`name`), default `serial<index>`.
    pub name: String,
    /// Port path (`address`, required): `/dev/ttyUSB0`, `COM3`...
    pub address: String,
    /// Line speed in bit/s (`baudRate`), default 57600; output is paced to it.
    pub baud_rate: u32,
    /// Initial and ceiling resend timeout for Safe frames (`TimeToResend`), default 1500 ms.
    pub time_to_resend: Duration,
    /// Largest frame payload before fragmenting (`MaxPacketSize`), default 300 bytes.
    pub max_packet_size: usize,
    /// Bound of the Fast queue, oldest dropped (`MaxMessageQueue`), default 20.
    pub max_message_queue: usize,
    /// Heartbeat period (`heartbeatMs`), default 5000 ms.
    pub heartbeat: Duration,
    /// A peer silent this long is gone (`leaseMs`), default 4 × heartbeat.
    pub lease: Duration,
}

impl Default for SerialConfig {
    /// The defaults with an empty `address`, which a real link must set.
    fn default() -> Self {
        Self {
            name: "serial0".to_owned(),
            address: String::new(),
            baud_rate: SERIAL_BAUD_RATE,
            time_to_resend: Duration::from_millis(SERIAL_TIME_TO_RESEND_MS),
            max_packet_size: SERIAL_MAX_PACKET_SIZE,
            max_message_queue: SERIAL_MAX_MESSAGE_QUEUE,
            heartbeat: Duration::from_millis(SERIAL_HEARTBEAT_MS),
            lease: Duration::from_millis(lease_ms(SERIAL_HEARTBEAT_MS, SERIAL_LEASE)),
        }
    }
}

/// A `<serialduo>` link: the Serial Transport Protocol over two one-way ports (two radio pairs).
#[derive(Debug, Clone, PartialEq)]
pub struct SerialDuoConfig {
    /// Link name (`name`), default `serialduo<index>`.
    pub name: String,
    /// Transmit port path (`addressTx`, required).
    pub address_tx: String,
    /// Transmit line speed in bit/s (`baudRateTx`), default 57600.
    pub baud_rate_tx: u32,
    /// Receive port path (`addressRx`, required, different from `addressTx`).
    pub address_rx: String,
    /// Receive line speed in bit/s (`baudRateRx`), default 57600.
    pub baud_rate_rx: u32,
    /// Initial and ceiling resend timeout for Safe frames (`TimeToResend`), default 1500 ms.
    pub time_to_resend: Duration,
    /// Largest frame payload before fragmenting (`MaxPacketSize`), default 300 bytes.
    pub max_packet_size: usize,
    /// Bound of the Fast queue, oldest dropped (`MaxMessageQueue`), default 20.
    pub max_message_queue: usize,
    /// Heartbeat period (`heartbeatMs`), default 5000 ms.
    pub heartbeat: Duration,
    /// A peer silent this long is gone (`leaseMs`), default 4 × heartbeat.
    pub lease: Duration,
}

impl Default for SerialDuoConfig {
    /// The defaults with empty addresses, which a real link must set.
    fn default() -> Self {
        Self {
            name: "serialduo0".to_owned(),
            address_tx: String::new(),
            baud_rate_tx: SERIAL_BAUD_RATE,
            address_rx: String::new(),
            baud_rate_rx: SERIAL_BAUD_RATE,
            time_to_resend: Duration::from_millis(SERIAL_TIME_TO_RESEND_MS),
            max_packet_size: SERIAL_MAX_PACKET_SIZE,
            max_message_queue: SERIAL_MAX_MESSAGE_QUEUE,
            heartbeat: Duration::from_millis(SERIAL_HEARTBEAT_MS),
            lease: Duration::from_millis(lease_ms(SERIAL_HEARTBEAT_MS, SERIAL_LEASE)),
        }
    }
}
