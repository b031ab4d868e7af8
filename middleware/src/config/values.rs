//! Defaults and limits of every attribute, and the syntax of attribute values (integers in a
//! range, booleans, names, addresses, ports), each refusal saying what was expected.

use std::net::{SocketAddr, SocketAddrV4};

use super::model::{ShmWait, ZenohMode};

/// Why a value did not parse; the caller adds the attribute and location.
pub(super) enum Invalid {
    /// Not of the form described.
    Syntax(&'static str),
    /// A whole number outside its range.
    Range(&'static IntSpec),
}

// ---------------------------------------------------------------------------------------------
// Defaults and limits

pub(super) const ETHERNET_HEARTBEAT_MS: u64 = 1000;
pub(super) const ETHERNET_LEASE: LeaseFactor = LeaseFactor { num: 7, den: 2 };
// Same-host peers die visibly (the process exits), so the LAN timing suits shared memory too.
pub(super) const SHM_HEARTBEAT_MS: u64 = 1000;
// A Zenoh link's peers are beyond a router, often over a WAN: the LAN's beat, and a lease that
// outlasts a router restart and a WAN outage of half a minute, so that nothing in flight is
// given up (a peer that leaves says Bye; only a crashed one takes the whole lease to notice).
pub(super) const ZENOH_HEARTBEAT_MS: u64 = 1000;
pub(super) const ZENOH_LEASE: LeaseFactor = LeaseFactor { num: 60, den: 1 };
pub(super) const SHM_LEASE: LeaseFactor = LeaseFactor { num: 7, den: 2 };
// Each peer an inbox admits costs ~11 KiB of the node's memory, touched at creation (iceoryx2
// keeps a connection entry per possible writer in each of the inbox's three buffers). Sixteen
// cover a vehicle's services on its computer; a host running more marea processes on one
// `service` raises it.
pub(super) const SHM_MAX_PEERS: u64 = 16;
// Serial radios are slow and lossy: a slower heartbeat keeps discovery off the air, a longer
// lease (in beats) survives a couple of lost heartbeats.
pub(super) const SERIAL_HEARTBEAT_MS: u64 = 5000;
pub(super) const SERIAL_LEASE: LeaseFactor = LeaseFactor { num: 4, den: 1 };
pub(super) const SERIAL_BAUD_RATE: u32 = 57_600;
pub(super) const SERIAL_TIME_TO_RESEND_MS: u64 = 1500;
pub(super) const SERIAL_MAX_PACKET_SIZE: usize = 300;
pub(super) const SERIAL_MAX_MESSAGE_QUEUE: usize = 20;

/// Default lease as a multiple of the heartbeat period.
#[derive(Clone, Copy)]
pub(super) struct LeaseFactor {
    num: u64,
    den: u64,
}

pub(super) const fn lease_ms(heartbeat_ms: u64, factor: LeaseFactor) -> u64 {
    heartbeat_ms.saturating_mul(factor.num) / factor.den
}

/// An integer attribute's allowed range and how to describe it.
pub(super) struct IntSpec {
    pub(super) min: u64,
    pub(super) max: u64,
    pub(super) expected: &'static str,
    pub(super) unit: &'static str,
}

impl IntSpec {
    const fn new(min: u64, max: u64, expected: &'static str, unit: &'static str) -> Self {
        Self {
            min,
            max,
            expected,
            unit,
        }
    }
}

pub(super) const HEARTBEAT_MS: IntSpec = IntSpec::new(
    1,
    3_600_000,
    "a positive integer in milliseconds",
    "milliseconds",
);
pub(super) const LEASE_MS: IntSpec = IntSpec::new(
    1,
    86_400_000,
    "a positive integer in milliseconds",
    "milliseconds",
);
pub(super) const MAX_PEERS: IntSpec =
    IntSpec::new(1, 1024, "an integer from 1 to 1024 (peers)", "peers");
pub(super) const TTL: IntSpec = IntSpec::new(0, 255, "an integer from 0 to 255", "hops");
pub(super) const BAUD_RATE: IntSpec = IntSpec::new(
    50,
    12_000_000,
    "a positive integer in bits per second",
    "bits per second",
);
pub(super) const TIME_TO_RESEND: IntSpec = IntSpec::new(
    1,
    600_000,
    "a positive integer in milliseconds",
    "milliseconds",
);
// A Serial Transport Protocol frame spends 9 bytes on type, sequence number, fragment index and
// total, and CRC32; below 32 bytes fragmentation would be mostly overhead. Above 65535 a frame
// would no longer be "a packet" on any radio we know.
pub(super) const MAX_PACKET_SIZE: IntSpec =
    IntSpec::new(32, 65_535, "a positive integer in bytes", "bytes");
pub(super) const MAX_MESSAGE_QUEUE: IntSpec =
    IntSpec::new(1, 65_536, "a positive integer (messages)", "messages");

pub(super) const NAME_SYNTAX: &str = "a name of letters, digits, '_' or '-'";
pub(super) const NAMESPACE_SYNTAX: &str = "names of letters, digits, '_' or '-' separated by '/'";
pub(super) const BOOL_SYNTAX: &str = "true or false";
pub(super) const YES_NO_SYNTAX: &str = "yes or no";
pub(super) const BIND_SYNTAX: &str = "a socket address like 0.0.0.0:0 or [::]:7400";
pub(super) const MULTICAST_SYNTAX: &str =
    "an IPv4 multicast group and non-zero port like 239.255.77.1:7477";
pub(super) const INTERFACE_SYNTAX: &str = "an IPv4 address like 127.0.0.1";
pub(super) const PEER_SYNTAX: &str =
    "a socket address with a specific IP and non-zero port like 192.0.2.10:7400";
pub(super) const PORT_SYNTAX: &str = "a serial port path like /dev/ttyUSB0 or COM3";
pub(super) const WAIT_SYNTAX: &str = "event or spin";

pub(super) const PEER_ELEMENTS: &[&str] = &["peer"];
pub(super) const NO_ELEMENTS: &[&str] = &[];
pub(super) const ACCESS_ELEMENTS: &[&str] = &["allow", "deny"];
pub(super) const ACCESS_ATTRS: &[&str] = &["trustClaims"];
pub(super) const ALLOW_ATTRS: &[&str] = &["kind", "item", "from"];
pub(super) const DENY_ATTRS: &[&str] = &["kind"];
pub(super) const ACCESS_KIND_SYNTAX: &str = "one of call, file, publish, gateway";
pub(super) const ACCESS_PATTERN_SYNTAX: &str =
    "a name pattern: segments of letters, digits, _ - . separated by /, or * and **";
/// What `<network>` may hold: the links, and the elements that are not links.
pub(super) const NETWORK_ELEMENTS: &[&str] = &[
    "ethernet",
    "shm",
    "serial",
    "serialduo",
    "zenoh",
    "security",
    "access",
];
pub(super) const SECURITY_ATTRS: &[&str] = &["keyFile", "encrypt", "identityFile", "identities"];
pub(super) const ENCRYPT_SYNTAX: &str = "`none` or `radio`";
pub(super) const PATH_SYNTAX: &str = "a file path";
pub(super) const KEY_FILE_SYNTAX: &str = "the path of a key file made by `usal keygen`";

pub(super) const NETWORK_ATTRS: &[&str] = &["node", "namespace", "domain", "gateway"];
pub(super) const ETHERNET_ATTRS: &[&str] = &[
    "name",
    "enabled",
    "bind",
    "multicast",
    "interface",
    "heartbeatMs",
    "leaseMs",
    "ttl",
];
pub(super) const PEER_ATTRS: &[&str] = &["address"];
pub(super) const ZENOH_ATTRS: &[&str] = &[
    "name",
    "enabled",
    "mode",
    "connect",
    "listen",
    "config",
    "heartbeatMs",
    "leaseMs",
];
pub(super) const ZENOH_MODE_SYNTAX: &str = "`client` (through a router) or `peer`";
pub(super) const ZENOH_ENDPOINTS_SYNTAX: &str =
    "Zenoh endpoints separated by commas, each `protocol/address` like tcp/10.0.0.1:7447 or tls/gs.example.org:7447";
pub(super) const SHM_ATTRS: &[&str] = &[
    "name",
    "enabled",
    "service",
    "heartbeatMs",
    "leaseMs",
    "wait",
    "maxPeers",
];
pub(super) const SERIAL_ATTRS: &[&str] = &[
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
pub(super) const SERIALDUO_ATTRS: &[&str] = &[
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
// Value syntax

pub(super) fn parse_int(s: &str, spec: &'static IntSpec) -> Result<u64, Invalid> {
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

pub(super) fn parse_encrypt(s: &str) -> Result<bool, Invalid> {
    match s.trim() {
        "none" => Ok(false),
        "radio" => Ok(true),
        _ => Err(Invalid::Syntax(ENCRYPT_SYNTAX)),
    }
}

pub(super) fn parse_bool(s: &str) -> Result<bool, Invalid> {
    match s.trim() {
        "true" | "1" => Ok(true),
        "false" | "0" => Ok(false),
        _ => Err(Invalid::Syntax(BOOL_SYNTAX)),
    }
}

/// A deliberate choice (`trustClaims`): `yes` or `no` (`true`/`false` taken too).
pub(super) fn parse_yes_no(s: &str) -> Result<bool, Invalid> {
    match s.trim() {
        "yes" | "true" => Ok(true),
        "no" | "false" => Ok(false),
        _ => Err(Invalid::Syntax(YES_NO_SYNTAX)),
    }
}

pub(super) fn is_name(s: &str) -> bool {
    !s.is_empty()
        && s.bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

pub(super) fn parse_name(s: &str, expected: &'static str) -> Result<String, Invalid> {
    if is_name(s) {
        Ok(s.to_owned())
    } else {
        Err(Invalid::Syntax(expected))
    }
}

pub(super) fn parse_namespace(s: &str) -> Result<String, Invalid> {
    if s.split('/').all(is_name) {
        Ok(s.to_owned())
    } else {
        Err(Invalid::Syntax(NAMESPACE_SYNTAX))
    }
}

pub(super) fn parse_bind(s: &str) -> Result<SocketAddr, Invalid> {
    s.trim().parse().map_err(|_| Invalid::Syntax(BIND_SYNTAX))
}

pub(super) fn parse_multicast(s: &str) -> Result<SocketAddrV4, Invalid> {
    match s.trim().parse::<SocketAddrV4>() {
        Ok(addr) if addr.ip().is_multicast() && addr.port() != 0 => Ok(addr),
        _ => Err(Invalid::Syntax(MULTICAST_SYNTAX)),
    }
}

pub(super) fn parse_peer(s: &str) -> Result<SocketAddr, Invalid> {
    match s.trim().parse::<SocketAddr>() {
        Ok(addr)
            if addr.port() != 0 && !addr.ip().is_unspecified() && !addr.ip().is_multicast() =>
        {
            Ok(addr)
        }
        _ => Err(Invalid::Syntax(PEER_SYNTAX)),
    }
}

pub(super) fn parse_wait(s: &str) -> Result<ShmWait, Invalid> {
    match s.trim() {
        "event" => Ok(ShmWait::Event),
        "spin" => Ok(ShmWait::Spin),
        _ => Err(Invalid::Syntax(WAIT_SYNTAX)),
    }
}

pub(super) fn parse_port(s: &str) -> Result<String, Invalid> {
    let s = s.trim();
    if s.is_empty() || s.chars().any(char::is_control) {
        Err(Invalid::Syntax(PORT_SYNTAX))
    } else {
        Ok(s.to_owned())
    }
}

pub(super) fn saturate_u32(v: u64) -> u32 {
    u32::try_from(v).unwrap_or(u32::MAX)
}

pub(super) fn saturate_usize(v: u64) -> usize {
    usize::try_from(v).unwrap_or(usize::MAX)
}

/// Keeps error messages readable when the offending text is long.
pub(super) fn shorten(s: &str) -> String {
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
pub(super) fn closest(found: &str, candidates: &'static [&'static str]) -> Option<&'static str> {
    let found_lower = found.to_ascii_lowercase();
    candidates
        .iter()
        .map(|&c| (edit_distance(&found_lower, &c.to_ascii_lowercase()), c))
        .filter(|&(d, c)| d <= (c.len() / 3).max(1))
        .min_by_key(|&(d, _)| d)
        .map(|(_, c)| c)
}

/// Levenshtein distance over characters.
pub(super) fn edit_distance(a: &str, b: &str) -> usize {
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

/// A `<zenoh mode>`.
pub(super) fn parse_zenoh_mode(s: &str) -> Result<ZenohMode, Invalid> {
    match s.trim() {
        "client" => Ok(ZenohMode::Client),
        "peer" => Ok(ZenohMode::Peer),
        _ => Err(Invalid::Syntax(ZENOH_MODE_SYNTAX)),
    }
}

/// A `<zenoh connect|listen>` list: `protocol/address` endpoints separated by commas (Zenoh
/// checks each protocol's address when the link opens).
pub(super) fn parse_zenoh_endpoints(s: &str) -> Result<Vec<String>, Invalid> {
    s.split(',')
        .map(str::trim)
        .filter(|e| !e.is_empty())
        .map(|e| {
            let (proto, addr) = e
                .split_once('/')
                .ok_or(Invalid::Syntax(ZENOH_ENDPOINTS_SYNTAX))?;
            let proto_ok = !proto.is_empty()
                && proto
                    .chars()
                    .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_');
            if proto_ok && !addr.trim().is_empty() && !e.contains(char::is_whitespace) {
                Ok(e.to_owned())
            } else {
                Err(Invalid::Syntax(ZENOH_ENDPOINTS_SYNTAX))
            }
        })
        .collect::<Result<Vec<_>, _>>()
        .and_then(|v| {
            if v.is_empty() {
                Err(Invalid::Syntax(ZENOH_ENDPOINTS_SYNTAX))
            } else {
                Ok(v)
            }
        })
}
