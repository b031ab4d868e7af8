//! `network.xml` loader: turns one node's link configuration file into a typed [`NetworkConfig`],
//! with errors that point at `file:line:column` and say what was expected.
//!
//! The file names the node, its namespace and discovery domain, and the links it talks on:
//!
//! ```xml
//! <network node="air" namespace="rover1" domain="usal">
//!   <ethernet name="lan" bind="0.0.0.0:0" multicast="239.255.77.1:7477" interface="127.0.0.1"
//!             heartbeatMs="1000" leaseMs="3500" ttl="1">
//!     <peer address="192.0.2.10:7400"/>
//!   </ethernet>
//!   <shm name="local" service="usal" wait="event"/>
//!   <serial name="radio" address="/dev/ttyUSB0" baudRate="57600" TimeToResend="1500"
//!           MaxPacketSize="300" MaxMessageQueue="20" heartbeatMs="5000" leaseMs="20000"/>
//!   <serialduo name="duo" addressTx="/dev/ttyUSB0" baudRateTx="115200" addressRx="/dev/ttyUSB1"
//!              baudRateRx="115200" TimeToResend="1500" MaxPacketSize="300" MaxMessageQueue="20"/>
//! </network>
//! ```
//!
//! The serial attribute names are the MAREA thesis' own, so a MAREA user recognises them. Every
//! link element also takes `enabled="false"` to switch it off without deleting or commenting it.
//! `config/network.xml` at the repository root is a fully commented example.
//!
//! The parser walks quick-xml's event reader by hand rather than using its serde deserializer,
//! because only the event reader gives byte positions for every element and attribute, and the
//! positions are what make a configuration error quick to fix.

use std::fmt;
use std::net::{Ipv4Addr, SocketAddr, SocketAddrV4};
use std::path::{Path, PathBuf};
use std::time::Duration;

use quick_xml::errors::IllFormedError;
use quick_xml::events::attributes::AttrError;
use quick_xml::events::{BytesStart, Event};
use quick_xml::Reader;

pub use crate::link::shm::ShmWait;

/// The discovery domain used when `<network>` has no `domain` attribute.
pub const DEFAULT_DOMAIN: &str = "usal";

/// One node's network configuration: who it is and which links it uses.
#[derive(Debug, Clone, PartialEq)]
pub struct NetworkConfig {
    /// This node's name (`node` attribute), `[A-Za-z0-9_-]+`.
    pub node: String,
    /// Prefix for this node's services' items (`rover1` gives `rover1/vas/position`); may be
    /// hierarchical (`fleet/rover1`). `None` when the attribute is absent.
    pub namespace: Option<String>,
    /// Isolation key: nodes of different domains ignore each other. Defaults to
    /// [`DEFAULT_DOMAIN`].
    pub domain: String,
    /// The enabled links, in file order. Links with `enabled="false"` are left out.
    pub links: Vec<LinkConfig>,
    /// Whether the node forwards between its links (`gateway` attribute). `None` (the
    /// default) forwards when a serial link sits beside another link: the radio gateway.
    pub gateway: Option<bool>,
    /// The file this configuration was read from, if any.
    pub source: Option<PathBuf>,
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
}

impl LinkConfig {
    /// The link's name, unique within a node (`ethernet0`, `radio`...).
    pub fn name(&self) -> &str {
        match self {
            LinkConfig::Ethernet(c) => &c.name,
            LinkConfig::Shm(c) => &c.name,
            LinkConfig::Serial(c) => &c.name,
            LinkConfig::SerialDuo(c) => &c.name,
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
    /// wakes it; `spin` busy-polls from a thread of its own, so writers never make a system
    /// call).
    pub wait: ShmWait,
}

impl Default for ShmConfig {
    fn default() -> Self {
        Self {
            name: "shm0".to_owned(),
            service: "usal".to_owned(),
            heartbeat: Duration::from_millis(SHM_HEARTBEAT_MS),
            lease: Duration::from_millis(lease_ms(SHM_HEARTBEAT_MS, SHM_LEASE)),
            wait: ShmWait::Event,
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

impl NetworkConfig {
    /// Reads and parses a `network.xml` file; [`NetworkConfig::source`] records `path`.
    ///
    /// # Errors
    /// [`ConfigLoadError::Unreadable`] when the file cannot be read,
    /// [`ConfigLoadError::NotUtf8`] when it is not UTF-8, and otherwise whatever
    /// [`NetworkConfig::parse`] reports.
    pub fn load(path: impl AsRef<Path>) -> Result<Self, ConfigLoadError> {
        let path = path.as_ref();
        let bytes = std::fs::read(path).map_err(|source| ConfigLoadError::Unreadable {
            path: path.to_path_buf(),
            source,
        })?;
        Self::parse_bytes(&bytes, Some(path))
    }

    /// Parses the text of a `network.xml`. `source` only names the text in errors and in
    /// [`NetworkConfig::source`]; nothing is read from it.
    ///
    /// # Errors
    /// Every other [`ConfigLoadError`] variant: malformed XML, an unexpected element, attribute
    /// or text, a missing or invalid value, or an inconsistent set of links. Each one carries the
    /// line and column of the offending element or attribute.
    pub fn parse(text: &str, source: Option<&Path>) -> Result<Self, ConfigLoadError> {
        Parser::new(text, source).document()
    }

    /// What a service process runs with: the file `network` when given, else
    /// [`NetworkConfig::ethernet_loopback`] for `node`; then `domain` and `namespace`, when
    /// given, override the file's (a launcher keeps one file per node and one domain per run).
    ///
    /// # Errors
    /// The file's [`ConfigLoadError`].
    pub fn for_service(
        network: Option<&Path>,
        node: &str,
        domain: Option<&str>,
        namespace: Option<&str>,
    ) -> Result<Self, ConfigLoadError> {
        let mut config = match network {
            Some(path) => Self::load(path)?,
            None => Self::ethernet_loopback(node),
        };
        if let Some(d) = domain {
            d.clone_into(&mut config.domain);
        }
        if let Some(ns) = namespace {
            config.namespace = Some(ns.to_owned());
        }
        Ok(config)
    }

    /// A configuration for `node` with one Ethernet link on the loopback interface (127.0.0.1)
    /// and defaults otherwise: handy for tests and single-host demos. `node` is not validated.
    pub fn ethernet_loopback(node: &str) -> Self {
        Self {
            node: node.to_owned(),
            namespace: None,
            domain: DEFAULT_DOMAIN.to_owned(),
            links: vec![LinkConfig::Ethernet(EthernetConfig {
                interface: Ipv4Addr::LOCALHOST,
                ..EthernetConfig::default()
            })],
            gateway: None,
            source: None,
        }
    }

    fn parse_bytes(bytes: &[u8], source: Option<&Path>) -> Result<Self, ConfigLoadError> {
        match std::str::from_utf8(bytes) {
            Ok(text) => Self::parse(text, source),
            Err(err) => {
                let valid = bytes.get(..err.valid_up_to()).unwrap_or_default();
                let (line, column) = line_column(valid, valid.len());
                Err(ConfigLoadError::NotUtf8 {
                    at: Location {
                        file: source.map(Box::from),
                        line,
                        column,
                    },
                    source: err,
                })
            }
        }
    }
}

/// A place in a `network.xml`: 1-based line and column (in characters).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Location {
    /// The file, or `None` for text given to [`NetworkConfig::parse`] without a source.
    // Boxed rather than a `PathBuf` to keep `ConfigLoadError` small (clippy::result_large_err).
    pub file: Option<Box<Path>>,
    /// Line number, from 1.
    pub line: usize,
    /// Column number in characters, from 1.
    pub column: usize,
}

impl fmt::Display for Location {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match &self.file {
            Some(file) => write!(f, "{}:{}:{}", file.display(), self.line, self.column),
            None => write!(f, "<input>:{}:{}", self.line, self.column),
        }
    }
}

/// Why a `network.xml` could not be loaded. Displays as `file:line:column: message`
/// (`<input>:line:column: ...` for text without a source).
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum ConfigLoadError {
    /// The file could not be read (missing, no permission, a directory...).
    #[error("{}: cannot read network config: {source}", path.display())]
    Unreadable {
        /// The path that was read.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The file is not UTF-8; `at` is the first invalid byte.
    #[error("{at}: not valid UTF-8: {source}")]
    NotUtf8 {
        /// Where.
        at: Location,
        /// The decoding error.
        #[source]
        source: std::str::Utf8Error,
    },
    /// The text is not well-formed XML (an unclosed tag, a bad attribute, an unknown entity...).
    #[error("{at}: malformed XML: {source}")]
    MalformedXml {
        /// Where.
        at: Location,
        /// quick-xml's description.
        #[source]
        source: quick_xml::Error,
    },
    /// The text holds no element at all.
    #[error("{at}: expected a <network> root element, found the end of the input")]
    NoRootElement {
        /// Where (the end of the input).
        at: Location,
    },
    /// The root element is not `<network>`.
    #[error("{at}: expected the root element <network>, found <{found}>")]
    WrongRoot {
        /// Where.
        at: Location,
        /// The root element's name.
        found: String,
    },
    /// An element that is not allowed where it appears.
    #[error("{at}: <{parent}>: unknown element <{found}>{}", element_hint(*.suggestion, expected))]
    UnknownElement {
        /// Where.
        at: Location,
        /// The enclosing element.
        parent: &'static str,
        /// The element found.
        found: String,
        /// A close allowed name, if any.
        suggestion: Option<&'static str>,
        /// The elements allowed there.
        expected: &'static [&'static str],
    },
    /// An attribute the element does not take.
    #[error("{at}: <{element}>: unknown attribute {found}{}", attribute_hint(*.suggestion, expected))]
    UnknownAttribute {
        /// Where.
        at: Location,
        /// The element.
        element: &'static str,
        /// The attribute found.
        found: String,
        /// A close allowed name, if any.
        suggestion: Option<&'static str>,
        /// The attributes the element takes.
        expected: &'static [&'static str],
    },
    /// The same attribute given twice on one element.
    #[error("{at}: <{element}>: attribute {attribute} given twice")]
    DuplicateAttribute {
        /// Where (the second occurrence).
        at: Location,
        /// The element.
        element: &'static str,
        /// The attribute.
        attribute: &'static str,
    },
    /// A required attribute is absent.
    #[error("{at}: <{element}>: missing required attribute {attribute} ({expected})")]
    MissingAttribute {
        /// Where (the element).
        at: Location,
        /// The element.
        element: &'static str,
        /// The attribute.
        attribute: &'static str,
        /// What it should hold.
        expected: &'static str,
    },
    /// An attribute value of the wrong form (not a number, address, boolean or name).
    #[error("{at}: <{element}>: attribute {attribute}: expected {expected}, found {found:?}")]
    BadValue {
        /// Where (the attribute).
        at: Location,
        /// The element.
        element: &'static str,
        /// The attribute.
        attribute: &'static str,
        /// What it should hold.
        expected: &'static str,
        /// The value found.
        found: String,
    },
    /// A number outside its allowed range.
    #[error(
        "{at}: <{element}>: attribute {attribute}: {found} is out of range, expected {min} to {max} {unit}"
    )]
    OutOfRange {
        /// Where (the attribute).
        at: Location,
        /// The element.
        element: &'static str,
        /// The attribute.
        attribute: &'static str,
        /// The value found.
        found: String,
        /// Smallest allowed value.
        min: u64,
        /// Largest allowed value.
        max: u64,
        /// Unit of the value.
        unit: &'static str,
    },
    /// `leaseMs` is not longer than the heartbeat period, so a live peer would be dropped.
    #[error(
        "{at}: <{element}>: attribute leaseMs: {lease_ms} must be greater than heartbeatMs ({heartbeat_ms})"
    )]
    LeaseNotAboveHeartbeat {
        /// Where (the `leaseMs` attribute).
        at: Location,
        /// The element.
        element: &'static str,
        /// The lease, in milliseconds.
        lease_ms: u64,
        /// The heartbeat period, in milliseconds.
        heartbeat_ms: u64,
    },
    /// Text (or CDATA, or an entity) where only elements and comments may appear.
    #[error("{at}: unexpected text {found:?} {}; only elements and comments are allowed", within(*.element))]
    UnexpectedText {
        /// Where.
        at: Location,
        /// The enclosing element, `None` outside the root.
        element: Option<&'static str>,
        /// The text found (shortened).
        found: String,
    },
    /// An element after the root element closed.
    #[error("{at}: unexpected <{found}> after the root element </network>")]
    TrailingContent {
        /// Where.
        at: Location,
        /// The element found.
        found: String,
    },
    /// `<network>` enables no link, so the node could talk to nobody.
    #[error(
        "{at}: <network>: no link; expected at least one enabled <ethernet>, <shm>, <serial> or <serialduo>"
    )]
    NoLinks {
        /// Where (the `<network>` element).
        at: Location,
    },
    /// Two links share a name (given or defaulted).
    #[error("{at}: duplicate link name {name:?} (first used at line {}, column {})", first.line, first.column)]
    DuplicateLinkName {
        /// Where (the second link's name, or the element when defaulted).
        at: Location,
        /// The name.
        name: String,
        /// Where the first link with this name is.
        first: Location,
    },
    /// A `<serialduo>` whose `addressTx` and `addressRx` are the same port.
    #[error(
        "{at}: <serialduo>: addressTx and addressRx are both {address:?}; a serialduo needs two different ports (use <serial> for one)"
    )]
    SerialDuoSamePort {
        /// Where (the `addressRx` attribute).
        at: Location,
        /// The port.
        address: String,
    },
    /// A serial port already used by another enabled link.
    #[error("{at}: serial port {address:?} is already used by link {first_link:?} (line {}, column {})", first.line, first.column)]
    SerialPortReused {
        /// Where (the second use).
        at: Location,
        /// The port.
        address: String,
        /// The link that uses it first.
        first_link: String,
        /// Where the first use is.
        first: Location,
    },
}

impl ConfigLoadError {
    /// Where the error is, when it is inside the text.
    pub fn location(&self) -> Option<&Location> {
        use ConfigLoadError as E;
        match self {
            E::Unreadable { .. } => None,
            E::NotUtf8 { at, .. }
            | E::MalformedXml { at, .. }
            | E::NoRootElement { at }
            | E::WrongRoot { at, .. }
            | E::UnknownElement { at, .. }
            | E::UnknownAttribute { at, .. }
            | E::DuplicateAttribute { at, .. }
            | E::MissingAttribute { at, .. }
            | E::BadValue { at, .. }
            | E::OutOfRange { at, .. }
            | E::LeaseNotAboveHeartbeat { at, .. }
            | E::UnexpectedText { at, .. }
            | E::TrailingContent { at, .. }
            | E::NoLinks { at }
            | E::DuplicateLinkName { at, .. }
            | E::SerialDuoSamePort { at, .. }
            | E::SerialPortReused { at, .. } => Some(at),
        }
    }

    /// The 1-based line of the error, when it is inside the text.
    pub fn line(&self) -> Option<usize> {
        self.location().map(|at| at.line)
    }

    /// The 1-based column (in characters) of the error, when it is inside the text.
    pub fn column(&self) -> Option<usize> {
        self.location().map(|at| at.column)
    }
}

fn element_hint(suggestion: Option<&str>, expected: &[&str]) -> String {
    match (suggestion, expected) {
        (Some(s), _) => format!(" (did you mean <{s}>?)"),
        (None, []) => "; no child elements are allowed here".to_owned(),
        (None, list) => {
            let names: Vec<String> = list.iter().map(|n| format!("<{n}>")).collect();
            format!("; expected {}", names.join(", "))
        }
    }
}

fn attribute_hint(suggestion: Option<&str>, expected: &[&str]) -> String {
    match suggestion {
        Some(s) => format!(" (did you mean {s}?)"),
        None => format!("; expected one of {}", expected.join(", ")),
    }
}

fn within(element: Option<&str>) -> String {
    match element {
        Some(e) => format!("inside <{e}>"),
        None => "outside the root element".to_owned(),
    }
}

// ---------------------------------------------------------------------------------------------
// Defaults and limits

const ETHERNET_HEARTBEAT_MS: u64 = 1000;
const ETHERNET_LEASE: LeaseFactor = LeaseFactor { num: 7, den: 2 };
// Same-host peers die visibly (the process exits), so the LAN timing suits shared memory too.
const SHM_HEARTBEAT_MS: u64 = 1000;
const SHM_LEASE: LeaseFactor = LeaseFactor { num: 7, den: 2 };
// Serial radios are slow and lossy: a slower heartbeat keeps discovery off the air, a longer
// lease (in beats) survives a couple of lost heartbeats.
const SERIAL_HEARTBEAT_MS: u64 = 5000;
const SERIAL_LEASE: LeaseFactor = LeaseFactor { num: 4, den: 1 };
const SERIAL_BAUD_RATE: u32 = 57_600;
const SERIAL_TIME_TO_RESEND_MS: u64 = 1500;
const SERIAL_MAX_PACKET_SIZE: usize = 300;
const SERIAL_MAX_MESSAGE_QUEUE: usize = 20;

/// Default lease as a multiple of the heartbeat period.
#[derive(Clone, Copy)]
struct LeaseFactor {
    num: u64,
    den: u64,
}

const fn lease_ms(heartbeat_ms: u64, factor: LeaseFactor) -> u64 {
    heartbeat_ms.saturating_mul(factor.num) / factor.den
}

/// An integer attribute's allowed range and how to describe it.
struct IntSpec {
    min: u64,
    max: u64,
    expected: &'static str,
    unit: &'static str,
}

const HEARTBEAT_MS: IntSpec = IntSpec {
    min: 1,
    max: 3_600_000,
    expected: "a positive integer in milliseconds",
    unit: "milliseconds",
};
const LEASE_MS: IntSpec = IntSpec {
    min: 1,
    max: 86_400_000,
    expected: "a positive integer in milliseconds",
    unit: "milliseconds",
};
const TTL: IntSpec = IntSpec {
    min: 0,
    max: 255,
    expected: "an integer from 0 to 255",
    unit: "hops",
};
const BAUD_RATE: IntSpec = IntSpec {
    min: 50,
    max: 12_000_000,
    expected: "a positive integer in bits per second",
    unit: "bits per second",
};
const TIME_TO_RESEND: IntSpec = IntSpec {
    min: 1,
    max: 600_000,
    expected: "a positive integer in milliseconds",
    unit: "milliseconds",
};
// A Serial Transport Protocol frame spends 9 bytes on type, sequence number, fragment index and
// total, and CRC32; below 32 bytes fragmentation would be mostly overhead. Above 65535 a frame
// would no longer be "a packet" on any radio we know.
const MAX_PACKET_SIZE: IntSpec = IntSpec {
    min: 32,
    max: 65_535,
    expected: "a positive integer in bytes",
    unit: "bytes",
};
const MAX_MESSAGE_QUEUE: IntSpec = IntSpec {
    min: 1,
    max: 65_536,
    expected: "a positive integer (messages)",
    unit: "messages",
};

const NAME_SYNTAX: &str = "a name of letters, digits, '_' or '-'";
const NAMESPACE_SYNTAX: &str = "names of letters, digits, '_' or '-' separated by '/'";
const BOOL_SYNTAX: &str = "true or false";
const BIND_SYNTAX: &str = "a socket address like 0.0.0.0:0 or [::]:7400";
const MULTICAST_SYNTAX: &str = "an IPv4 multicast group and non-zero port like 239.255.77.1:7477";
const INTERFACE_SYNTAX: &str = "an IPv4 address like 127.0.0.1";
const PEER_SYNTAX: &str =
    "a socket address with a specific IP and non-zero port like 192.0.2.10:7400";
const PORT_SYNTAX: &str = "a serial port path like /dev/ttyUSB0 or COM3";
const WAIT_SYNTAX: &str = "event or spin";

const LINK_ELEMENTS: &[&str] = &["ethernet", "shm", "serial", "serialduo"];
const PEER_ELEMENTS: &[&str] = &["peer"];
const NO_ELEMENTS: &[&str] = &[];

const NETWORK_ATTRS: &[&str] = &["node", "namespace", "domain", "gateway"];
const ETHERNET_ATTRS: &[&str] = &[
    "name",
    "enabled",
    "bind",
    "multicast",
    "interface",
    "heartbeatMs",
    "leaseMs",
    "ttl",
];
const PEER_ATTRS: &[&str] = &["address"];
const SHM_ATTRS: &[&str] = &[
    "name",
    "enabled",
    "service",
    "heartbeatMs",
    "leaseMs",
    "wait",
];
const SERIAL_ATTRS: &[&str] = &[
    "name",
    "enabled",
    "address",
    "baudRate",
    "TimeToResend",
    "MaxPacketSize",
    "MaxMessageQueue",
    "heartbeatMs",
    "leaseMs",
];
const SERIALDUO_ATTRS: &[&str] = &[
    "name",
    "enabled",
    "addressTx",
    "baudRateTx",
    "addressRx",
    "baudRateRx",
    "TimeToResend",
    "MaxPacketSize",
    "MaxMessageQueue",
    "heartbeatMs",
    "leaseMs",
];

// ---------------------------------------------------------------------------------------------
// Parser

/// The attributes of one element, checked against the element's allowed list.
struct Attrs {
    element: &'static str,
    /// Byte offset of the element's `<`.
    offset: usize,
    list: Vec<Attr>,
}

struct Attr {
    key: &'static str,
    value: String,
    /// Byte offset of the attribute's name.
    offset: usize,
}

impl Attrs {
    fn get(&self, key: &str) -> Option<&Attr> {
        self.list.iter().find(|a| a.key == key)
    }

    /// Where `key` is, or where the element is when `key` is absent.
    fn offset_of(&self, key: &str) -> usize {
        self.get(key).map_or(self.offset, |a| a.offset)
    }
}

/// Why a value did not parse; the caller adds the attribute and location.
enum Invalid {
    Syntax(&'static str),
    Range(&'static IntSpec),
}

/// An element's start tag and where it is.
struct Element<'a> {
    /// Byte offset of its `<`.
    offset: usize,
    start: BytesStart<'a>,
    /// `false` for an empty-element tag (`<x/>`).
    has_children: bool,
}

/// What a parsed link contributes to the cross-link checks.
struct ParsedLink {
    link: LinkConfig,
    enabled: bool,
    name_at: Location,
    /// Serial ports it opens, with where each is named.
    ports: Vec<(String, Location)>,
}

struct Parser<'a> {
    text: &'a str,
    source: Option<&'a Path>,
    reader: Reader<&'a [u8]>,
}

impl<'a> Parser<'a> {
    fn new(text: &'a str, source: Option<&'a Path>) -> Self {
        let mut reader = Reader::from_str(text);
        let config = reader.config_mut();
        config.trim_text(false);
        config.check_end_names = true;
        config.check_comments = true;
        config.expand_empty_elements = false;
        Self {
            text,
            source,
            reader,
        }
    }

    fn at(&self, offset: usize) -> Location {
        let (line, column) = line_column(self.text.as_bytes(), offset);
        Location {
            file: self.source.map(Box::from),
            line,
            column,
        }
    }

    /// The next event, with the byte offset where it starts.
    fn event(&mut self) -> Result<(usize, Event<'a>), ConfigLoadError> {
        let before = to_usize(self.reader.buffer_position());
        match self.reader.read_event() {
            Ok(event) => {
                // The reader may skip a byte-order mark before the first event, so locate the
                // tag's `<` rather than trusting the previous end position.
                let offset = match event {
                    Event::Start(_) | Event::Empty(_) => self
                        .text
                        .as_bytes()
                        .get(before..)
                        .and_then(|rest| rest.iter().position(|&b| b == b'<'))
                        .map_or(before, |i| before + i),
                    _ => before,
                };
                Ok((offset, event))
            }
            Err(source) => Err(ConfigLoadError::MalformedXml {
                at: self.at(to_usize(self.reader.error_position())),
                source,
            }),
        }
    }

    fn document(mut self) -> Result<NetworkConfig, ConfigLoadError> {
        let config = loop {
            let (offset, event) = self.event()?;
            match event {
                Event::Start(start) => {
                    break self.network(&Element {
                        offset,
                        start,
                        has_children: true,
                    })?
                }
                Event::Empty(start) => {
                    break self.network(&Element {
                        offset,
                        start,
                        has_children: false,
                    })?
                }
                Event::Eof => {
                    return Err(ConfigLoadError::NoRootElement {
                        at: self.at(self.text.len()),
                    })
                }
                other => self.misc(offset, &other, None)?,
            }
        };
        loop {
            let (offset, event) = self.event()?;
            match event {
                Event::Start(start) | Event::Empty(start) => {
                    return Err(ConfigLoadError::TrailingContent {
                        at: self.at(offset),
                        found: element_name(&start),
                    })
                }
                Event::Eof => return Ok(config),
                other => self.misc(offset, &other, None)?,
            }
        }
    }

    /// Accepts whitespace, comments, the XML declaration, processing instructions and a
    /// DOCTYPE; rejects text, CDATA and entity references. Called for every event that is not an
    /// element start, an element end or the end of input. (quick-xml rejects unmatched end tags
    /// itself, so an end tag never reaches here.)
    fn misc(
        &self,
        offset: usize,
        event: &Event<'a>,
        element: Option<&'static str>,
    ) -> Result<(), ConfigLoadError> {
        let (skip, found) = match event {
            Event::Text(text) => match text.iter().position(|b| !b" \t\r\n".contains(b)) {
                None => return Ok(()),
                Some(first) => (first, String::from_utf8_lossy(text).trim().to_owned()),
            },
            Event::CData(data) => (0, format!("<![CDATA[{}]]>", String::from_utf8_lossy(data))),
            Event::GeneralRef(name) => (0, format!("&{};", String::from_utf8_lossy(name))),
            _ => return Ok(()),
        };
        Err(ConfigLoadError::UnexpectedText {
            at: self.at(offset + skip),
            element,
            found: shorten(&found),
        })
    }

    /// The next child element of `parent`, or `None` once `parent` has ended. Call it until it
    /// returns `None`, and no further.
    fn child(
        &mut self,
        name: &'static str,
        parent: &Element<'a>,
    ) -> Result<Option<Element<'a>>, ConfigLoadError> {
        if !parent.has_children {
            return Ok(None);
        }
        loop {
            let (offset, event) = self.event()?;
            let (start, has_children) = match event {
                Event::Start(start) => (start, true),
                Event::Empty(start) => (start, false),
                // quick-xml checks that end names match, so this is `parent`'s end.
                Event::End(_) => return Ok(None),
                // quick-xml reports a missing end tag only as the end of input.
                Event::Eof => {
                    return Err(ConfigLoadError::MalformedXml {
                        at: self.at(parent.offset),
                        source: IllFormedError::MissingEndTag(name.to_owned()).into(),
                    })
                }
                other => {
                    self.misc(offset, &other, Some(name))?;
                    continue;
                }
            };
            return Ok(Some(Element {
                offset,
                start,
                has_children,
            }));
        }
    }

    /// Consumes the content of an element that takes no child elements.
    fn no_children(
        &mut self,
        name: &'static str,
        element: &Element<'a>,
    ) -> Result<(), ConfigLoadError> {
        match self.child(name, element)? {
            None => Ok(()),
            Some(child) => Err(self.unknown_element(name, &child, NO_ELEMENTS)),
        }
    }

    fn unknown_element(
        &self,
        parent: &'static str,
        child: &Element<'_>,
        expected: &'static [&'static str],
    ) -> ConfigLoadError {
        let found = element_name(&child.start);
        ConfigLoadError::UnknownElement {
            at: self.at(child.offset),
            parent,
            suggestion: closest(&found, expected),
            found,
            expected,
        }
    }

    /// Reads an element's attributes, rejecting unknown and repeated ones.
    fn attributes(
        &self,
        name: &'static str,
        element: &Element<'_>,
        allowed: &'static [&'static str],
    ) -> Result<Attrs, ConfigLoadError> {
        // Attribute positions are relative to the tag's content, which starts after `<`.
        let base = element.offset + 1;
        let content: &[u8] = &element.start;
        let mut attrs = Attrs {
            element: name,
            offset: element.offset,
            list: Vec::new(),
        };
        // Duplicates are checked below, to report them with the attribute's name.
        for attribute in element.start.attributes().with_checks(false) {
            let attribute = attribute.map_err(|err| ConfigLoadError::MalformedXml {
                at: self.at(base + attr_error_offset(&err)),
                source: err.into(),
            })?;
            let key_bytes = attribute.key.as_ref();
            // The key is a slice of the tag's content; its address gives its position.
            let relative = (key_bytes.as_ptr() as usize).wrapping_sub(content.as_ptr() as usize);
            let at = base + relative.min(content.len());
            let key = String::from_utf8_lossy(key_bytes);
            if key == "xmlns" || key.starts_with("xmlns:") {
                continue;
            }
            let Some(&known) = allowed.iter().find(|&&name| name == key) else {
                return Err(ConfigLoadError::UnknownAttribute {
                    at: self.at(at),
                    element: name,
                    suggestion: closest(&key, allowed),
                    found: key.into_owned(),
                    expected: allowed,
                });
            };
            if attrs.get(known).is_some() {
                return Err(ConfigLoadError::DuplicateAttribute {
                    at: self.at(at),
                    element: name,
                    attribute: known,
                });
            }
            let value =
                attribute
                    .unescape_value()
                    .map_err(|source| ConfigLoadError::MalformedXml {
                        at: self.at(at),
                        source,
                    })?;
            attrs.list.push(Attr {
                key: known,
                value: value.into_owned(),
                offset: at,
            });
        }
        Ok(attrs)
    }

    /// Parses an optional attribute with `parse`.
    fn value<T>(
        &self,
        attrs: &Attrs,
        key: &'static str,
        parse: impl FnOnce(&str) -> Result<T, Invalid>,
    ) -> Result<Option<T>, ConfigLoadError> {
        let Some(attr) = attrs.get(key) else {
            return Ok(None);
        };
        parse(&attr.value)
            .map(Some)
            .map_err(|invalid| match invalid {
                Invalid::Syntax(expected) => ConfigLoadError::BadValue {
                    at: self.at(attr.offset),
                    element: attrs.element,
                    attribute: key,
                    expected,
                    found: attr.value.clone(),
                },
                Invalid::Range(spec) => ConfigLoadError::OutOfRange {
                    at: self.at(attr.offset),
                    element: attrs.element,
                    attribute: key,
                    found: attr.value.trim().to_owned(),
                    min: spec.min,
                    max: spec.max,
                    unit: spec.unit,
                },
            })
    }

    /// Parses a required attribute with `parse`.
    fn required<T>(
        &self,
        attrs: &Attrs,
        key: &'static str,
        expected: &'static str,
        parse: impl FnOnce(&str) -> Result<T, Invalid>,
    ) -> Result<T, ConfigLoadError> {
        self.value(attrs, key, parse)?
            .ok_or_else(|| ConfigLoadError::MissingAttribute {
                at: self.at(attrs.offset),
                element: attrs.element,
                attribute: key,
                expected,
            })
    }

    fn int(
        &self,
        attrs: &Attrs,
        key: &'static str,
        spec: &'static IntSpec,
    ) -> Result<Option<u64>, ConfigLoadError> {
        self.value(attrs, key, |s| parse_int(s, spec))
    }

    /// `heartbeatMs` and `leaseMs`, the lease defaulting to a multiple of the heartbeat.
    fn timing(
        &self,
        attrs: &Attrs,
        default_heartbeat_ms: u64,
        factor: LeaseFactor,
    ) -> Result<(Duration, Duration), ConfigLoadError> {
        let heartbeat_ms = self
            .int(attrs, "heartbeatMs", &HEARTBEAT_MS)?
            .unwrap_or(default_heartbeat_ms);
        let lease_ms = match self.int(attrs, "leaseMs", &LEASE_MS)? {
            Some(lease) if lease <= heartbeat_ms => {
                return Err(ConfigLoadError::LeaseNotAboveHeartbeat {
                    at: self.at(attrs.offset_of("leaseMs")),
                    element: attrs.element,
                    lease_ms: lease,
                    heartbeat_ms,
                })
            }
            Some(lease) => lease,
            None => lease_ms(heartbeat_ms, factor),
        };
        Ok((
            Duration::from_millis(heartbeat_ms),
            Duration::from_millis(lease_ms),
        ))
    }

    /// `enabled` (default true) and `name` (default `<kind><index>`) with where the name is.
    fn link_common(
        &self,
        attrs: &Attrs,
        index: usize,
    ) -> Result<(bool, String, Location), ConfigLoadError> {
        let enabled = self.value(attrs, "enabled", parse_bool)?.unwrap_or(true);
        let name = self
            .value(attrs, "name", |s| parse_name(s, NAME_SYNTAX))?
            .unwrap_or_else(|| format!("{}{index}", attrs.element));
        let name_at = self.at(attrs.offset_of("name"));
        Ok((enabled, name, name_at))
    }

    fn network(&mut self, root: &Element<'a>) -> Result<NetworkConfig, ConfigLoadError> {
        let found = element_name(&root.start);
        if found != "network" {
            return Err(ConfigLoadError::WrongRoot {
                at: self.at(root.offset),
                found,
            });
        }
        let attrs = self.attributes("network", root, NETWORK_ATTRS)?;
        let node = self.required(&attrs, "node", NAME_SYNTAX, |s| parse_name(s, NAME_SYNTAX))?;
        let namespace = self.value(&attrs, "namespace", parse_namespace)?;
        let domain = self
            .value(&attrs, "domain", |s| parse_name(s, NAME_SYNTAX))?
            .unwrap_or_else(|| DEFAULT_DOMAIN.to_owned());
        let gateway = self.value(&attrs, "gateway", parse_bool)?;

        let mut links = Vec::new();
        let mut names: Vec<(String, Location)> = Vec::new();
        let mut ports: Vec<(String, String, Location)> = Vec::new();
        // Kinds of the link elements so far, for default names (`<kind><index>`). Disabled
        // links count too, so that switching one off does not rename the others.
        let mut kinds: Vec<String> = Vec::new();
        while let Some(child) = self.child("network", root)? {
            let kind = element_name(&child.start);
            let index = kinds.iter().filter(|&k| *k == kind).count();
            let parsed = match kind.as_str() {
                "ethernet" => self.ethernet(&child, index)?,
                "shm" => self.shm(&child, index)?,
                "serial" => self.serial(&child, index)?,
                "serialduo" => self.serialduo(&child, index)?,
                _ => return Err(self.unknown_element("network", &child, LINK_ELEMENTS)),
            };
            kinds.push(kind);
            let name = parsed.link.name().to_owned();
            if let Some((_, first)) = names.iter().find(|(n, _)| *n == name) {
                return Err(ConfigLoadError::DuplicateLinkName {
                    at: parsed.name_at,
                    name,
                    first: first.clone(),
                });
            }
            names.push((name.clone(), parsed.name_at));
            if !parsed.enabled {
                continue;
            }
            for (address, at) in parsed.ports {
                if let Some((_, first_link, first)) = ports.iter().find(|(a, ..)| *a == address) {
                    return Err(ConfigLoadError::SerialPortReused {
                        at,
                        address,
                        first_link: first_link.clone(),
                        first: first.clone(),
                    });
                }
                ports.push((address, name.clone(), at));
            }
            links.push(parsed.link);
        }
        if links.is_empty() {
            return Err(ConfigLoadError::NoLinks {
                at: self.at(root.offset),
            });
        }
        Ok(NetworkConfig {
            node,
            namespace,
            domain,
            links,
            gateway,
            source: self.source.map(Path::to_path_buf),
        })
    }

    fn ethernet(
        &mut self,
        element: &Element<'a>,
        index: usize,
    ) -> Result<ParsedLink, ConfigLoadError> {
        let attrs = self.attributes("ethernet", element, ETHERNET_ATTRS)?;
        let (enabled, name, name_at) = self.link_common(&attrs, index)?;
        let defaults = EthernetConfig::default();
        let bind = self
            .value(&attrs, "bind", parse_bind)?
            .unwrap_or(defaults.bind);
        let multicast = self
            .value(&attrs, "multicast", parse_multicast)?
            .unwrap_or(defaults.multicast);
        let interface = self
            .value(&attrs, "interface", |s| {
                s.trim()
                    .parse()
                    .map_err(|_| Invalid::Syntax(INTERFACE_SYNTAX))
            })?
            .unwrap_or(defaults.interface);
        let (heartbeat, lease) = self.timing(&attrs, ETHERNET_HEARTBEAT_MS, ETHERNET_LEASE)?;
        let ttl = self
            .int(&attrs, "ttl", &TTL)?
            .map_or(defaults.ttl, saturate_u32);

        let mut peers = Vec::new();
        while let Some(peer) = self.child("ethernet", element)? {
            if element_name(&peer.start) != "peer" {
                return Err(self.unknown_element("ethernet", &peer, PEER_ELEMENTS));
            }
            let attrs = self.attributes("peer", &peer, PEER_ATTRS)?;
            peers.push(self.required(&attrs, "address", PEER_SYNTAX, parse_peer)?);
            self.no_children("peer", &peer)?;
        }
        Ok(ParsedLink {
            link: LinkConfig::Ethernet(EthernetConfig {
                name,
                bind,
                multicast,
                interface,
                heartbeat,
                lease,
                ttl,
                peers,
            }),
            enabled,
            name_at,
            ports: Vec::new(),
        })
    }

    fn shm(&mut self, element: &Element<'a>, index: usize) -> Result<ParsedLink, ConfigLoadError> {
        let attrs = self.attributes("shm", element, SHM_ATTRS)?;
        let (enabled, name, name_at) = self.link_common(&attrs, index)?;
        let service = self
            .value(&attrs, "service", |s| parse_name(s, NAME_SYNTAX))?
            .unwrap_or_else(|| ShmConfig::default().service);
        let (heartbeat, lease) = self.timing(&attrs, SHM_HEARTBEAT_MS, SHM_LEASE)?;
        let wait = self.value(&attrs, "wait", parse_wait)?.unwrap_or_default();
        self.no_children("shm", element)?;
        Ok(ParsedLink {
            link: LinkConfig::Shm(ShmConfig {
                name,
                service,
                heartbeat,
                lease,
                wait,
            }),
            enabled,
            name_at,
            ports: Vec::new(),
        })
    }

    /// `TimeToResend`, `MaxPacketSize` and `MaxMessageQueue`, shared by both serial kinds.
    fn serial_protocol(&self, attrs: &Attrs) -> Result<(Duration, usize, usize), ConfigLoadError> {
        let time_to_resend = self
            .int(attrs, "TimeToResend", &TIME_TO_RESEND)?
            .unwrap_or(SERIAL_TIME_TO_RESEND_MS);
        let max_packet_size = self
            .int(attrs, "MaxPacketSize", &MAX_PACKET_SIZE)?
            .map_or(SERIAL_MAX_PACKET_SIZE, saturate_usize);
        let max_message_queue = self
            .int(attrs, "MaxMessageQueue", &MAX_MESSAGE_QUEUE)?
            .map_or(SERIAL_MAX_MESSAGE_QUEUE, saturate_usize);
        Ok((
            Duration::from_millis(time_to_resend),
            max_packet_size,
            max_message_queue,
        ))
    }

    fn serial(
        &mut self,
        element: &Element<'a>,
        index: usize,
    ) -> Result<ParsedLink, ConfigLoadError> {
        let attrs = self.attributes("serial", element, SERIAL_ATTRS)?;
        let (enabled, name, name_at) = self.link_common(&attrs, index)?;
        let address = self.required(&attrs, "address", PORT_SYNTAX, parse_port)?;
        let address_at = self.at(attrs.offset_of("address"));
        let baud_rate = self
            .int(&attrs, "baudRate", &BAUD_RATE)?
            .map_or(SERIAL_BAUD_RATE, saturate_u32);
        let (time_to_resend, max_packet_size, max_message_queue) = self.serial_protocol(&attrs)?;
        let (heartbeat, lease) = self.timing(&attrs, SERIAL_HEARTBEAT_MS, SERIAL_LEASE)?;
        self.no_children("serial", element)?;
        Ok(ParsedLink {
            ports: vec![(address.clone(), address_at)],
            link: LinkConfig::Serial(SerialConfig {
                name,
                address,
                baud_rate,
                time_to_resend,
                max_packet_size,
                max_message_queue,
                heartbeat,
                lease,
            }),
            enabled,
            name_at,
        })
    }

    fn serialduo(
        &mut self,
        element: &Element<'a>,
        index: usize,
    ) -> Result<ParsedLink, ConfigLoadError> {
        let attrs = self.attributes("serialduo", element, SERIALDUO_ATTRS)?;
        let (enabled, name, name_at) = self.link_common(&attrs, index)?;
        let address_tx = self.required(&attrs, "addressTx", PORT_SYNTAX, parse_port)?;
        let baud_rate_tx = self
            .int(&attrs, "baudRateTx", &BAUD_RATE)?
            .map_or(SERIAL_BAUD_RATE, saturate_u32);
        let address_rx = self.required(&attrs, "addressRx", PORT_SYNTAX, parse_port)?;
        let baud_rate_rx = self
            .int(&attrs, "baudRateRx", &BAUD_RATE)?
            .map_or(SERIAL_BAUD_RATE, saturate_u32);
        let tx_at = self.at(attrs.offset_of("addressTx"));
        let rx_at = self.at(attrs.offset_of("addressRx"));
        if address_tx == address_rx {
            return Err(ConfigLoadError::SerialDuoSamePort {
                at: rx_at,
                address: address_rx,
            });
        }
        let (time_to_resend, max_packet_size, max_message_queue) = self.serial_protocol(&attrs)?;
        let (heartbeat, lease) = self.timing(&attrs, SERIAL_HEARTBEAT_MS, SERIAL_LEASE)?;
        self.no_children("serialduo", element)?;
        Ok(ParsedLink {
            ports: vec![(address_tx.clone(), tx_at), (address_rx.clone(), rx_at)],
            link: LinkConfig::SerialDuo(SerialDuoConfig {
                name,
                address_tx,
                baud_rate_tx,
                address_rx,
                baud_rate_rx,
                time_to_resend,
                max_packet_size,
                max_message_queue,
                heartbeat,
                lease,
            }),
            enabled,
            name_at,
        })
    }
}

// ---------------------------------------------------------------------------------------------
// Value syntax

fn parse_int(s: &str, spec: &'static IntSpec) -> Result<u64, Invalid> {
    let s = s.trim();
    if s.is_empty() || !s.bytes().all(|b| b.is_ascii_digit()) {
        return Err(Invalid::Syntax(spec.expected));
    }
    // All digits, so the only way to fail is overflow: that is a range error.
    match s.parse::<u64>() {
        Ok(v) if (spec.min..=spec.max).contains(&v) => Ok(v),
        _ => Err(Invalid::Range(spec)),
    }
}

fn parse_bool(s: &str) -> Result<bool, Invalid> {
    match s.trim() {
        "true" | "1" => Ok(true),
        "false" | "0" => Ok(false),
        _ => Err(Invalid::Syntax(BOOL_SYNTAX)),
    }
}

fn is_name(s: &str) -> bool {
    !s.is_empty()
        && s.bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

fn parse_name(s: &str, expected: &'static str) -> Result<String, Invalid> {
    if is_name(s) {
        Ok(s.to_owned())
    } else {
        Err(Invalid::Syntax(expected))
    }
}

fn parse_namespace(s: &str) -> Result<String, Invalid> {
    if s.split('/').all(is_name) {
        Ok(s.to_owned())
    } else {
        Err(Invalid::Syntax(NAMESPACE_SYNTAX))
    }
}

fn parse_bind(s: &str) -> Result<SocketAddr, Invalid> {
    s.trim().parse().map_err(|_| Invalid::Syntax(BIND_SYNTAX))
}

fn parse_multicast(s: &str) -> Result<SocketAddrV4, Invalid> {
    match s.trim().parse::<SocketAddrV4>() {
        Ok(addr) if addr.ip().is_multicast() && addr.port() != 0 => Ok(addr),
        _ => Err(Invalid::Syntax(MULTICAST_SYNTAX)),
    }
}

fn parse_peer(s: &str) -> Result<SocketAddr, Invalid> {
    match s.trim().parse::<SocketAddr>() {
        Ok(addr)
            if addr.port() != 0 && !addr.ip().is_unspecified() && !addr.ip().is_multicast() =>
        {
            Ok(addr)
        }
        _ => Err(Invalid::Syntax(PEER_SYNTAX)),
    }
}

fn parse_wait(s: &str) -> Result<ShmWait, Invalid> {
    match s.trim() {
        "event" => Ok(ShmWait::Event),
        "spin" => Ok(ShmWait::Spin),
        _ => Err(Invalid::Syntax(WAIT_SYNTAX)),
    }
}

fn parse_port(s: &str) -> Result<String, Invalid> {
    let s = s.trim();
    if s.is_empty() || s.chars().any(char::is_control) {
        Err(Invalid::Syntax(PORT_SYNTAX))
    } else {
        Ok(s.to_owned())
    }
}

// ---------------------------------------------------------------------------------------------
// Helpers

fn element_name(start: &BytesStart<'_>) -> String {
    String::from_utf8_lossy(start.name().as_ref()).into_owned()
}

fn attr_error_offset(err: &AttrError) -> usize {
    match *err {
        AttrError::ExpectedEq(p)
        | AttrError::ExpectedValue(p)
        | AttrError::UnquotedValue(p)
        | AttrError::ExpectedQuote(p, _)
        | AttrError::Duplicated(p, _) => p,
    }
}

/// 1-based line and column (in characters) of byte `offset` in `bytes`.
fn line_column(bytes: &[u8], offset: usize) -> (usize, usize) {
    let before = bytes.get(..offset.min(bytes.len())).unwrap_or_default();
    let line_start = before
        .iter()
        .rposition(|&b| b == b'\n')
        .map_or(0, |i| i + 1);
    let line = before.iter().filter(|&&b| b == b'\n').count() + 1;
    // Count characters, not bytes: UTF-8 continuation bytes look like 0b10xx_xxxx.
    let column = before
        .get(line_start..)
        .unwrap_or_default()
        .iter()
        .filter(|&&b| b & 0xC0 != 0x80)
        .count()
        + 1;
    (line, column)
}

fn to_usize(position: u64) -> usize {
    usize::try_from(position).unwrap_or(usize::MAX)
}

fn saturate_u32(v: u64) -> u32 {
    u32::try_from(v).unwrap_or(u32::MAX)
}

fn saturate_usize(v: u64) -> usize {
    usize::try_from(v).unwrap_or(usize::MAX)
}

/// Keeps error messages readable when the offending text is long.
fn shorten(s: &str) -> String {
    const MAX: usize = 40;
    if s.chars().count() <= MAX {
        s.to_owned()
    } else {
        let mut short: String = s.chars().take(MAX).collect();
        short.push('…');
        short
    }
}

/// The allowed name closest to `found`, if close enough to be a likely typo.
fn closest(found: &str, candidates: &'static [&'static str]) -> Option<&'static str> {
    let found_lower = found.to_ascii_lowercase();
    candidates
        .iter()
        .map(|&c| (edit_distance(&found_lower, &c.to_ascii_lowercase()), c))
        .filter(|&(d, c)| d <= (c.len() / 3).max(1))
        .min_by_key(|&(d, _)| d)
        .map(|(_, c)| c)
}

/// Levenshtein distance over characters.
fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut previous: Vec<usize> = (0..=b.len()).collect();
    let mut current = vec![0; b.len() + 1];
    for (i, ca) in a.chars().enumerate() {
        current[0] = i + 1;
        for (j, &cb) in b.iter().enumerate() {
            let substitute = previous[j] + usize::from(ca != cb);
            current[j + 1] = substitute.min(previous[j + 1] + 1).min(current[j] + 1);
        }
        std::mem::swap(&mut previous, &mut current);
    }
    previous[b.len()]
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const EXAMPLE: &str = r#"<network node="air" namespace="rover1" domain="usal">
  <!-- a comment -->
  <ethernet name="lan" bind="0.0.0.0:0" multicast="239.255.77.1:7477" interface="127.0.0.1" heartbeatMs="1000" leaseMs="3500" ttl="1">
    <peer address="192.0.2.10:7400"/>
  </ethernet>
  <shm name="local" service="usal" wait="spin"/>
  <serial name="radio" address="/dev/ttyUSB0" baudRate="57600" TimeToResend="1500" MaxPacketSize="300" MaxMessageQueue="20" heartbeatMs="5000" leaseMs="20000"/>
  <serialduo name="duo" addressTx="/dev/ttyUSB2" baudRateTx="115200" addressRx="/dev/ttyUSB1" baudRateRx="115200" TimeToResend="1500" MaxPacketSize="300" MaxMessageQueue="20"/>
</network>
"#;

    fn ms(v: u64) -> Duration {
        Duration::from_millis(v)
    }

    fn parse(text: &str) -> Result<NetworkConfig, ConfigLoadError> {
        NetworkConfig::parse(text, None)
    }

    /// Parses `text` as `config/network.xml`, expecting an error.
    fn error(text: &str) -> ConfigLoadError {
        match NetworkConfig::parse(text, Some(Path::new("config/network.xml"))) {
            Ok(config) => panic!("expected an error, parsed {config:?}"),
            Err(err) => err,
        }
    }

    /// The error message for `text` and its line and column.
    fn message(text: &str) -> (String, usize, usize) {
        let err = error(text);
        let (line, column) = (err.line().unwrap(), err.column().unwrap());
        (err.to_string(), line, column)
    }

    /// Wraps link elements in a valid root on line 1, so the links start on line 2.
    fn net(links: &str) -> String {
        format!("<network node=\"n\">\n{links}\n</network>")
    }

    #[test]
    fn a_service_config_takes_the_launcher_overrides() {
        let c = NetworkConfig::for_service(None, "vas", Some("run-7"), Some("rover1")).unwrap();
        assert_eq!(c.node, "vas");
        assert_eq!(c.domain, "run-7");
        assert_eq!(c.namespace.as_deref(), Some("rover1"));
        let c = NetworkConfig::for_service(None, "vas", None, None).unwrap();
        assert_eq!((c.domain.as_str(), c.namespace), (DEFAULT_DOMAIN, None));
        let e =
            NetworkConfig::for_service(Some(Path::new("/nonexistent/n.xml")), "vas", None, None)
                .unwrap_err()
                .to_string();
        assert!(e.starts_with("/nonexistent/n.xml: cannot read"), "{e}");
    }

    #[test]
    fn example_parses_into_the_exact_config() {
        let config = parse(EXAMPLE).unwrap();
        let expected = NetworkConfig {
            node: "air".into(),
            namespace: Some("rover1".into()),
            domain: "usal".into(),
            links: vec![
                LinkConfig::Ethernet(EthernetConfig {
                    name: "lan".into(),
                    bind: "0.0.0.0:0".parse().unwrap(),
                    multicast: "239.255.77.1:7477".parse().unwrap(),
                    interface: Ipv4Addr::LOCALHOST,
                    heartbeat: ms(1000),
                    lease: ms(3500),
                    ttl: 1,
                    peers: vec!["192.0.2.10:7400".parse().unwrap()],
                }),
                LinkConfig::Shm(ShmConfig {
                    name: "local".into(),
                    service: "usal".into(),
                    heartbeat: ms(1000),
                    lease: ms(3500),
                    wait: ShmWait::Spin,
                }),
                LinkConfig::Serial(SerialConfig {
                    name: "radio".into(),
                    address: "/dev/ttyUSB0".into(),
                    baud_rate: 57600,
                    time_to_resend: ms(1500),
                    max_packet_size: 300,
                    max_message_queue: 20,
                    heartbeat: ms(5000),
                    lease: ms(20000),
                }),
                LinkConfig::SerialDuo(SerialDuoConfig {
                    name: "duo".into(),
                    address_tx: "/dev/ttyUSB2".into(),
                    baud_rate_tx: 115_200,
                    address_rx: "/dev/ttyUSB1".into(),
                    baud_rate_rx: 115_200,
                    time_to_resend: ms(1500),
                    max_packet_size: 300,
                    max_message_queue: 20,
                    heartbeat: ms(5000),
                    lease: ms(20000),
                }),
            ],
            gateway: None,
            source: None,
        };
        assert_eq!(config, expected);
        let names: Vec<&str> = config.links.iter().map(LinkConfig::name).collect();
        assert_eq!(names, ["lan", "local", "radio", "duo"]);
    }

    #[test]
    fn defaults() {
        let text = r#"<?xml version="1.0"?>
<network node="n">
  <ethernet/>
  <shm></shm>
  <serial address="/dev/ttyS0"/>
  <serialduo addressTx="/dev/ttyS1" addressRx="/dev/ttyS2"/>
</network>"#;
        let config = parse(text).unwrap();
        assert_eq!(config.node, "n");
        assert_eq!(config.namespace, None);
        assert_eq!(config.domain, "usal");
        assert_eq!(
            config.links,
            [
                LinkConfig::Ethernet(EthernetConfig {
                    name: "ethernet0".into(),
                    bind: "0.0.0.0:0".parse().unwrap(),
                    multicast: "239.255.77.1:7477".parse().unwrap(),
                    interface: Ipv4Addr::UNSPECIFIED,
                    heartbeat: ms(1000),
                    lease: ms(3500),
                    ttl: 1,
                    peers: vec![],
                }),
                LinkConfig::Shm(ShmConfig {
                    name: "shm0".into(),
                    service: "usal".into(),
                    heartbeat: ms(1000),
                    lease: ms(3500),
                    wait: ShmWait::Event,
                }),
                LinkConfig::Serial(SerialConfig {
                    name: "serial0".into(),
                    address: "/dev/ttyS0".into(),
                    baud_rate: 57600,
                    time_to_resend: ms(1500),
                    max_packet_size: 300,
                    max_message_queue: 20,
                    heartbeat: ms(5000),
                    lease: ms(20000),
                }),
                LinkConfig::SerialDuo(SerialDuoConfig {
                    name: "serialduo0".into(),
                    address_tx: "/dev/ttyS1".into(),
                    baud_rate_tx: 57600,
                    address_rx: "/dev/ttyS2".into(),
                    baud_rate_rx: 57600,
                    time_to_resend: ms(1500),
                    max_packet_size: 300,
                    max_message_queue: 20,
                    heartbeat: ms(5000),
                    lease: ms(20000),
                }),
            ]
        );
        // The `Default` impls agree with the parser's defaults.
        assert_eq!(
            config.links[0],
            LinkConfig::Ethernet(EthernetConfig::default())
        );
        assert_eq!(config.links[1], LinkConfig::Shm(ShmConfig::default()));
    }

    #[test]
    fn lease_defaults_follow_the_heartbeat() {
        let config = parse(&net(
            r#"<ethernet heartbeatMs="200"/><serial address="a" heartbeatMs="3000"/>"#,
        ))
        .unwrap();
        let LinkConfig::Ethernet(eth) = &config.links[0] else {
            panic!()
        };
        assert_eq!((eth.heartbeat, eth.lease), (ms(200), ms(700)));
        let LinkConfig::Serial(serial) = &config.links[1] else {
            panic!()
        };
        assert_eq!((serial.heartbeat, serial.lease), (ms(3000), ms(12000)));
    }

    #[test]
    fn default_names_count_per_kind_including_disabled_links() {
        let config = parse(&net(
            r#"<ethernet/><ethernet enabled="false"/><shm/><ethernet interface="127.0.0.1"/>"#,
        ))
        .unwrap();
        let names: Vec<&str> = config.links.iter().map(LinkConfig::name).collect();
        assert_eq!(names, ["ethernet0", "shm0", "ethernet2"]);
    }

    #[test]
    fn namespace_domain_peers_ipv6_and_entities() {
        let config = parse(
            r#"<network node="g-1" namespace="fleet/rover_1" domain="d2" xmlns="urn:x">
            <ethernet bind="[::1]:7400" name="a&amp;b-ok">
              <peer address="10.0.0.1:1"/><peer address="[fe80::1]:7400"></peer>
            </ethernet></network>"#,
        );
        // `a&b-ok` unescapes to a name with '&', which name syntax refuses.
        assert!(matches!(
            config,
            Err(ConfigLoadError::BadValue {
                attribute: "name",
                ..
            })
        ));
        let config = parse(
            r#"<network node="g-1" namespace="fleet/rover_1" domain="d2" xmlns="urn:x">
            <ethernet bind="[::1]:7400"><peer address="10.0.0.1:1"/><peer address="[fe80::1]:7400"></peer></ethernet>
            </network>"#,
        )
        .unwrap();
        assert_eq!(config.namespace.as_deref(), Some("fleet/rover_1"));
        assert_eq!(config.domain, "d2");
        let LinkConfig::Ethernet(eth) = &config.links[0] else {
            panic!()
        };
        assert_eq!(eth.bind, "[::1]:7400".parse().unwrap());
        assert_eq!(eth.peers.len(), 2);
    }

    #[test]
    fn ethernet_loopback() {
        let config = NetworkConfig::ethernet_loopback("air");
        assert_eq!(config.node, "air");
        assert_eq!(config.domain, "usal");
        assert_eq!(
            config.links,
            [LinkConfig::Ethernet(EthernetConfig {
                interface: Ipv4Addr::LOCALHOST,
                ..EthernetConfig::default()
            })]
        );
        assert_eq!(config.links[0].name(), "ethernet0");
    }

    #[test]
    fn example_config_loads() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../config/network.xml");
        let config = NetworkConfig::load(path).unwrap();
        assert_eq!(config.node, "air");
        assert_eq!(config.namespace.as_deref(), Some("rover1"));
        assert_eq!(config.source.as_deref(), Some(Path::new(path)));
        let [LinkConfig::Ethernet(eth)] = config.links.as_slice() else {
            panic!("expected one ethernet link, got {:?}", config.links);
        };
        assert_eq!(eth.interface, Ipv4Addr::LOCALHOST);
    }

    #[test]
    fn load_records_the_source_and_names_it_in_errors() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("network.xml");
        std::fs::write(&path, EXAMPLE).unwrap();
        let config = NetworkConfig::load(&path).unwrap();
        assert_eq!(config.source.as_deref(), Some(path.as_path()));

        std::fs::write(&path, "<network node=\"a\"/>").unwrap();
        let err = NetworkConfig::load(&path).unwrap_err();
        assert!(
            err.to_string()
                .starts_with(&format!("{}:1:1: <network>: no link", path.display())),
            "{err}"
        );
    }

    // ---- one test per error kind ------------------------------------------------------------

    #[test]
    fn unreadable_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("missing.xml");
        let err = NetworkConfig::load(&path).unwrap_err();
        assert!(matches!(err, ConfigLoadError::Unreadable { .. }));
        assert_eq!((err.line(), err.column()), (None, None));
        let text = err.to_string();
        assert!(
            text.starts_with(&format!("{}: cannot read network config: ", path.display())),
            "{text}"
        );
        // A directory is unreadable too.
        let err = NetworkConfig::load(dir.path()).unwrap_err();
        assert!(matches!(err, ConfigLoadError::Unreadable { .. }));
    }

    #[test]
    fn not_utf8() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("network.xml");
        std::fs::write(&path, b"<network node=\"a\">\n  <x\xffy/>").unwrap();
        let err = NetworkConfig::load(&path).unwrap_err();
        assert!(matches!(err, ConfigLoadError::NotUtf8 { .. }), "{err}");
        assert_eq!((err.line(), err.column()), (Some(2), Some(5)));
        assert!(
            err.to_string()
                .starts_with(&format!("{}:2:5: not valid UTF-8", path.display())),
            "{err}"
        );
    }

    #[test]
    fn malformed_xml() {
        // A mismatched end tag: quick-xml's position is the `</`.
        let (text, line, column) = message("<network node=\"n\">\n  <ethernet>\n  </network>");
        assert_eq!((line, column), (3, 3));
        assert_eq!(
            text,
            "config/network.xml:3:3: malformed XML: ill-formed document: expected `</ethernet>`, but `</network>` was found"
        );
        // An unclosed root is reported at its start tag.
        let (text, line, column) = message("<network node=\"n\">\n  <ethernet/>\n");
        assert_eq!((line, column), (1, 1));
        assert!(
            text.contains("`</network>` not found before end of input"),
            "{text}"
        );
        // An unclosed child likewise.
        let (_, line, column) = message("<network node=\"n\">\n  <ethernet>\n");
        assert_eq!((line, column), (2, 3));
        // Attribute syntax: an unquoted value, positioned at the value.
        let (text, line, column) = message("<network node=\"n\">\n  <ethernet ttl=1/>\n</network>");
        assert_eq!((line, column), (2, 17));
        assert!(text.contains("malformed XML"), "{text}");
        // An unknown entity in an attribute value, positioned at the attribute.
        let (text, line, column) =
            message("<network node=\"n\">\n  <shm service=\"a&bogus;\"/>\n</network>");
        assert_eq!((line, column), (2, 8));
        assert!(text.contains("malformed XML"), "{text}");
        // A tag cut short.
        let (_, line, column) = message("<network node=\"n\">\n  <ethernet");
        assert_eq!((line, column), (2, 3));
    }

    #[test]
    fn no_root_element() {
        for text in ["", "  \n", "<?xml version=\"1.0\"?>\n<!-- nothing -->\n"] {
            let err = error(text);
            assert!(
                matches!(err, ConfigLoadError::NoRootElement { .. }),
                "{err}"
            );
        }
        let (text, line, column) = message("<!-- nothing -->\n");
        assert_eq!((line, column), (2, 1));
        assert_eq!(
            text,
            "config/network.xml:2:1: expected a <network> root element, found the end of the input"
        );
    }

    #[test]
    fn wrong_root() {
        let (text, line, column) =
            message("<?xml version=\"1.0\"?>\n<!-- x -->\n<netwrk node=\"a\"/>");
        assert_eq!((line, column), (3, 1));
        assert_eq!(
            text,
            "config/network.xml:3:1: expected the root element <network>, found <netwrk>"
        );
    }

    #[test]
    fn unknown_element() {
        let (text, line, column) = message(&net("  <ethernett/>"));
        assert_eq!((line, column), (2, 3));
        assert_eq!(
            text,
            "config/network.xml:2:3: <network>: unknown element <ethernett> (did you mean <ethernet>?)"
        );
        let (text, ..) = message(&net("<radio/>"));
        assert_eq!(
            text,
            "config/network.xml:2:1: <network>: unknown element <radio>; expected <ethernet>, <shm>, <serial>, <serialduo>"
        );
        let (text, line, column) = message(&net("<shm>\n    <peer/>\n</shm>"));
        assert_eq!((line, column), (3, 5));
        assert_eq!(
            text,
            "config/network.xml:3:5: <shm>: unknown element <peer>; no child elements are allowed here"
        );
        let (text, ..) = message(&net("<ethernet><per address=\"1.2.3.4:5\"/></ethernet>"));
        assert_eq!(
            text,
            "config/network.xml:2:11: <ethernet>: unknown element <per> (did you mean <peer>?)"
        );
    }

    #[test]
    fn unknown_attribute() {
        let (text, line, column) = message(&net("  <ethernet\n      heartbeatMS=\"1000\"/>"));
        assert_eq!((line, column), (3, 7));
        assert_eq!(
            text,
            "config/network.xml:3:7: <ethernet>: unknown attribute heartbeatMS (did you mean heartbeatMs?)"
        );
        let (text, ..) = message(&net(r#"<serial address="a" timeToResend="5"/>"#));
        assert!(
            text.ends_with("unknown attribute timeToResend (did you mean TimeToResend?)"),
            "{text}"
        );
        let (text, line, column) = message(r#"<network node="a" color="red"><shm/></network>"#);
        assert_eq!((line, column), (1, 19));
        assert_eq!(
            text,
            "config/network.xml:1:19: <network>: unknown attribute color; expected one of node, namespace, domain, gateway"
        );
    }

    #[test]
    fn duplicate_attribute() {
        let (text, line, column) = message(&net(r#"<shm name="a" name="b"/>"#));
        assert_eq!((line, column), (2, 15));
        assert_eq!(
            text,
            "config/network.xml:2:15: <shm>: attribute name given twice"
        );
    }

    #[test]
    fn missing_attribute() {
        let (text, line, column) = message("\n<network><shm/></network>");
        assert_eq!((line, column), (2, 1));
        assert_eq!(
            text,
            "config/network.xml:2:1: <network>: missing required attribute node (a name of letters, digits, '_' or '-')"
        );
        let (text, ..) = message(&net("  <serial baudRate=\"9600\"/>"));
        assert_eq!(
            text,
            "config/network.xml:2:3: <serial>: missing required attribute address (a serial port path like /dev/ttyUSB0 or COM3)"
        );
        let (text, ..) = message(&net(r#"<serialduo addressTx="a"/>"#));
        assert!(text.ends_with("missing required attribute addressRx (a serial port path like /dev/ttyUSB0 or COM3)"), "{text}");
        let (text, ..) = message(&net("<ethernet><peer/></ethernet>"));
        assert!(
            text.starts_with("config/network.xml:2:11: <peer>: missing required attribute address"),
            "{text}"
        );
    }

    #[test]
    fn bad_value() {
        // The example from the brief: an attribute at line 7, column 5.
        let text = "<network node=\"air\">\n  <!-- radio -->\n\n\n  <ethernet\n    name=\"lan\"\n    heartbeatMs=\"fast\"/>\n</network>";
        let (text, line, column) = message(text);
        assert_eq!((line, column), (7, 5));
        assert_eq!(
            text,
            "config/network.xml:7:5: <ethernet>: attribute heartbeatMs: expected a positive integer in milliseconds, found \"fast\""
        );
        let cases = [
            (r#"<ethernet bind="localhost:80"/>"#, "attribute bind: expected a socket address like 0.0.0.0:0 or [::]:7400, found \"localhost:80\""),
            (r#"<ethernet multicast="192.168.1.1:7477"/>"#, "attribute multicast: expected an IPv4 multicast group and non-zero port like 239.255.77.1:7477, found \"192.168.1.1:7477\""),
            (r#"<ethernet multicast="239.1.1.1:0"/>"#, "attribute multicast: expected an IPv4 multicast group and non-zero port like 239.255.77.1:7477, found \"239.1.1.1:0\""),
            (r#"<ethernet interface="eth0"/>"#, "attribute interface: expected an IPv4 address like 127.0.0.1, found \"eth0\""),
            (r#"<ethernet ttl="-1"/>"#, "attribute ttl: expected an integer from 0 to 255, found \"-1\""),
            (r#"<ethernet><peer address="0.0.0.0:7400"/></ethernet>"#, "attribute address: expected a socket address with a specific IP and non-zero port like 192.0.2.10:7400, found \"0.0.0.0:7400\""),
            (r#"<shm enabled="yes"/>"#, "attribute enabled: expected true or false, found \"yes\""),
            (r#"<shm name="my link"/>"#, "attribute name: expected a name of letters, digits, '_' or '-', found \"my link\""),
            (r#"<shm service=""/>"#, "attribute service: expected a name of letters, digits, '_' or '-', found \"\""),
            (r#"<shm wait="poll"/>"#, "attribute wait: expected event or spin, found \"poll\""),
            (r#"<serial address="  "/>"#, "attribute address: expected a serial port path like /dev/ttyUSB0 or COM3, found \"  \""),
            (r#"<serial address="a" baudRate="fast"/>"#, "attribute baudRate: expected a positive integer in bits per second, found \"fast\""),
            (r#"<serial address="a" MaxPacketSize="1.5"/>"#, "attribute MaxPacketSize: expected a positive integer in bytes, found \"1.5\""),
        ];
        for (links, expected) in cases {
            let (text, line, _) = message(&net(links));
            assert_eq!(line, 2, "{text}");
            assert!(
                text.ends_with(expected),
                "{text}\n  expected it to end with {expected}"
            );
        }
        let (text, ..) = message(r#"<network node="a/b"><shm/></network>"#);
        assert!(
            text.ends_with(
                "attribute node: expected a name of letters, digits, '_' or '-', found \"a/b\""
            ),
            "{text}"
        );
        let (text, ..) = message(r#"<network node="a" namespace="rover1/"><shm/></network>"#);
        assert!(text.ends_with("attribute namespace: expected names of letters, digits, '_' or '-' separated by '/', found \"rover1/\""), "{text}");
        let (text, ..) = message(r#"<network node="a" domain="x.y"><shm/></network>"#);
        assert!(text.contains("attribute domain: expected a name"), "{text}");
    }

    #[test]
    fn out_of_range() {
        let (text, line, column) = message(&net(r#"<serial address="a" MaxPacketSize="10"/>"#));
        assert_eq!((line, column), (2, 21));
        assert_eq!(
            text,
            "config/network.xml:2:21: <serial>: attribute MaxPacketSize: 10 is out of range, expected 32 to 65535 bytes"
        );
        let cases = [
            (r#"<serial address="a" MaxPacketSize="70000"/>"#, "MaxPacketSize: 70000 is out of range, expected 32 to 65535 bytes"),
            (r#"<serial address="a" baudRate="0"/>"#, "baudRate: 0 is out of range, expected 50 to 12000000 bits per second"),
            (r#"<serialduo addressTx="a" addressRx="b" baudRateRx="0"/>"#, "baudRateRx: 0 is out of range, expected 50 to 12000000 bits per second"),
            (r#"<serial address="a" MaxMessageQueue="0"/>"#, "MaxMessageQueue: 0 is out of range, expected 1 to 65536 messages"),
            (r#"<serial address="a" TimeToResend="0"/>"#, "TimeToResend: 0 is out of range, expected 1 to 600000 milliseconds"),
            (r#"<ethernet ttl="256"/>"#, "ttl: 256 is out of range, expected 0 to 255 hops"),
            (r#"<ethernet heartbeatMs="0"/>"#, "heartbeatMs: 0 is out of range, expected 1 to 3600000 milliseconds"),
            (r#"<shm leaseMs="99999999999999999999999"/>"#, "leaseMs: 99999999999999999999999 is out of range, expected 1 to 86400000 milliseconds"),
        ];
        for (links, expected) in cases {
            let err = error(&net(links));
            assert!(matches!(err, ConfigLoadError::OutOfRange { .. }), "{err}");
            let text = err.to_string();
            assert!(
                text.ends_with(expected),
                "{text}\n  expected it to end with {expected}"
            );
        }
    }

    #[test]
    fn lease_not_above_heartbeat() {
        let (text, line, column) =
            message(&net(r#"<ethernet heartbeatMs="1000" leaseMs="1000"/>"#));
        assert_eq!((line, column), (2, 30));
        assert_eq!(
            text,
            "config/network.xml:2:30: <ethernet>: attribute leaseMs: 1000 must be greater than heartbeatMs (1000)"
        );
        // Against the default heartbeat too.
        let (text, ..) = message(&net(r#"<serial address="a" leaseMs="4000"/>"#));
        assert!(
            text.ends_with("leaseMs: 4000 must be greater than heartbeatMs (5000)"),
            "{text}"
        );
    }

    #[test]
    fn unexpected_text() {
        let (text, line, column) = message(&net("  <shm/> oops"));
        assert_eq!((line, column), (2, 10));
        assert_eq!(
            text,
            "config/network.xml:2:10: unexpected text \"oops\" inside <network>; only elements and comments are allowed"
        );
        let (text, ..) = message("stray <network node=\"a\"><shm/></network>");
        assert!(
            text.starts_with(
                "config/network.xml:1:1: unexpected text \"stray\" outside the root element"
            ),
            "{text}"
        );
        let (text, ..) = message(&net("<shm><![CDATA[x]]></shm>"));
        assert!(
            text.contains("unexpected text \"<![CDATA[x]]>\" inside <shm>"),
            "{text}"
        );
        let (text, ..) = message(&net("<ethernet>&amp;</ethernet>"));
        assert!(
            text.contains("unexpected text \"&amp;\" inside <ethernet>"),
            "{text}"
        );
    }

    #[test]
    fn trailing_content() {
        let (text, line, column) = message(&format!("{}\n<network node=\"b\"/>", net("<shm/>")));
        assert_eq!((line, column), (4, 1));
        assert_eq!(
            text,
            "config/network.xml:4:1: unexpected <network> after the root element </network>"
        );
        let (text, ..) = message(&format!("{} trailing", net("<shm/>")));
        assert!(
            text.contains("unexpected text \"trailing\" outside the root element"),
            "{text}"
        );
    }

    #[test]
    fn no_links() {
        for text in [
            "<network node=\"n\"/>",
            "<network node=\"n\">\n  <!-- <ethernet/> -->\n</network>",
            "<network node=\"n\"><shm enabled=\"false\"/><ethernet enabled=\"0\"/></network>",
        ] {
            let (message, line, column) = message(text);
            assert_eq!((line, column), (1, 1));
            assert_eq!(
                message,
                "config/network.xml:1:1: <network>: no link; expected at least one enabled <ethernet>, <shm>, <serial> or <serialduo>"
            );
        }
    }

    #[test]
    fn duplicate_link_names() {
        let (text, line, column) = message(&net("<shm name=\"lan\"/>\n<ethernet name=\"lan\"/>"));
        assert_eq!((line, column), (3, 11));
        assert_eq!(
            text,
            "config/network.xml:3:11: duplicate link name \"lan\" (first used at line 2, column 6)"
        );
        // A given name clashing with a default one; the defaulted link is located by its element.
        let (text, line, column) = message(&net("<shm name=\"ethernet0\"/> <ethernet/>"));
        assert_eq!((line, column), (2, 25));
        assert!(
            text.ends_with("duplicate link name \"ethernet0\" (first used at line 2, column 6)"),
            "{text}"
        );
        // Disabled links keep their names reserved.
        let err = error(&net("<shm name=\"x\" enabled=\"false\"/><shm name=\"x\"/>"));
        assert!(
            matches!(err, ConfigLoadError::DuplicateLinkName { .. }),
            "{err}"
        );
    }

    #[test]
    fn serialduo_same_port() {
        let (text, line, column) = message(&net(
            r#"<serialduo addressTx="/dev/ttyUSB0" addressRx="/dev/ttyUSB0"/>"#,
        ));
        assert_eq!((line, column), (2, 37));
        assert_eq!(
            text,
            "config/network.xml:2:37: <serialduo>: addressTx and addressRx are both \"/dev/ttyUSB0\"; a serialduo needs two different ports (use <serial> for one)"
        );
    }

    #[test]
    fn serial_port_reused() {
        let (text, line, column) = message(&net(
            "<serial name=\"radio\" address=\"/dev/ttyUSB0\"/>\n<serialduo addressTx=\"/dev/ttyUSB1\" addressRx=\"/dev/ttyUSB0\"/>",
        ));
        assert_eq!((line, column), (3, 37));
        assert_eq!(
            text,
            "config/network.xml:3:37: serial port \"/dev/ttyUSB0\" is already used by link \"radio\" (line 2, column 22)"
        );
        // A disabled link opens no port.
        parse(&net(
            "<serial address=\"/dev/ttyUSB0\" enabled=\"false\"/><serial address=\"/dev/ttyUSB0\"/>",
        ))
        .unwrap();
    }

    #[test]
    fn positions_without_a_source_and_in_characters() {
        let err = parse("<!--é✈--><network node=\"x\"/>").unwrap_err();
        assert!(err.to_string().starts_with("<input>:1:10: "), "{err}");
        let err = parse("<network node=\"n\">\n\t<shm/> ✈ x</network>").unwrap_err();
        assert_eq!((err.line(), err.column()), (Some(2), Some(9)));
        // A byte-order mark does not shift columns of the first line.
        let err = parse("\u{feff}<netwrk/>").unwrap_err();
        assert_eq!((err.line(), err.column()), (Some(1), Some(2)));
    }

    #[test]
    fn crlf_line_endings_parse() {
        let text = EXAMPLE.replace('\n', "\r\n");
        assert_eq!(parse(&text).unwrap(), parse(EXAMPLE).unwrap());
    }

    // ---- never panic ------------------------------------------------------------------------

    /// A random edit of a valid file: delete, insert or replace a span.
    #[derive(Debug, Clone)]
    enum Edit {
        Delete(usize, usize),
        Insert(usize, String),
        Replace(usize, usize, String),
    }

    fn edit() -> impl Strategy<Value = Edit> {
        let fragment = prop_oneof![
            "[<>/=\"'&;!?\\- a-zA-Z0-9:.\\[\\]\n]{0,12}",
            Just("<".to_owned()),
            Just("\"".to_owned()),
            Just("<![CDATA[".to_owned()),
            Just("<!--".to_owned()),
            Just("&#x0;".to_owned()),
            Just("<peer address=\"1.2.3.4:5\"/>".to_owned()),
            Just("<ethernet>".to_owned()),
            Just("</network>".to_owned()),
            Just(" name=\"lan\"".to_owned()),
            Just("99999999999999999999".to_owned()),
            Just("é✈\u{feff}".to_owned()),
        ];
        prop_oneof![
            (any::<usize>(), 0..20_usize).prop_map(|(at, len)| Edit::Delete(at, len)),
            (any::<usize>(), fragment.clone()).prop_map(|(at, s)| Edit::Insert(at, s)),
            (any::<usize>(), 0..8_usize, fragment)
                .prop_map(|(at, len, s)| Edit::Replace(at, len, s)),
        ]
    }

    /// Applies `edit` to `text` at character boundaries.
    fn apply(text: &mut String, edit: &Edit) {
        let boundary = |text: &str, at: usize| {
            let mut at = at % (text.len() + 1);
            while !text.is_char_boundary(at) {
                at -= 1;
            }
            at
        };
        match edit {
            Edit::Delete(at, len) | Edit::Replace(at, len, _) => {
                let start = boundary(text, *at);
                let end = boundary(text, start.saturating_add(*len).min(text.len()));
                let with = match edit {
                    Edit::Replace(.., s) => s.as_str(),
                    _ => "",
                };
                text.replace_range(start..end.max(start), with);
            }
            Edit::Insert(at, s) => {
                let at = boundary(text, *at);
                text.insert_str(at, s);
            }
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(2000))]

        #[test]
        fn random_bytes_never_panic(bytes in proptest::collection::vec(any::<u8>(), 0..512)) {
            let _ = NetworkConfig::parse_bytes(&bytes, None);
            let _ = NetworkConfig::parse(&String::from_utf8_lossy(&bytes), None);
        }

        #[test]
        fn mutated_example_never_panics(edits in proptest::collection::vec(edit(), 1..6)) {
            let mut text = EXAMPLE.to_owned();
            for edit in &edits {
                apply(&mut text, edit);
            }
            match NetworkConfig::parse(&text, Some(Path::new("x.xml"))) {
                Ok(config) => prop_assert!(!config.links.is_empty()),
                Err(err) => {
                    // Every error inside the text has a plausible position and a message.
                    let line = err.line().unwrap();
                    prop_assert!(line >= 1 && line <= text.lines().count() + 1);
                    prop_assert!(err.column().unwrap() >= 1);
                    prop_assert!(err.to_string().starts_with("x.xml:"));
                }
            }
        }
    }
}
