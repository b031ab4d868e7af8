//! Tests of `network.xml` loading: the exact config of the example, defaults, and one test per
//! error kind with its message, line and column. A file of its own because they exercise the
//! whole module through [`NetworkConfig::parse`], not one of its files.

use super::*;
use proptest::prelude::*;
use std::net::Ipv4Addr;
use std::path::Path;
use std::time::Duration;

const EXAMPLE: &str = r#"<network node="air" namespace="rover1" domain="usal">
  <!-- a comment -->
  <ethernet name="lan" bind="0.0.0.0:0" multicast="239.255.77.1:7477" interface="127.0.0.1" heartbeatMs="1000" leaseMs="3500" ttl="1">
    <peer address="192.0.2.10:7400"/>
  </ethernet>
  <shm name="local" service="usal" wait="spin" maxPeers="8"/>
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
    let e = NetworkConfig::for_service(Some(Path::new("/nonexistent/n.xml")), "vas", None, None)
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
                max_peers: 8,
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
        access: None,
        security: None,
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
                max_peers: 16,
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
fn a_zenoh_link_takes_its_endpoints_mode_and_file_and_defaults_to_a_client() {
    let c = NetworkConfig::parse(
        &net(r#"<zenoh connect="tcp/10.0.0.1:7447, tls/gs.example.org:7447" config="z.json5"/>"#),
        Some(Path::new("/etc/usal/network.xml")),
    )
    .unwrap();
    assert_eq!(
        c.links,
        vec![LinkConfig::Zenoh(ZenohConfig {
            name: "zenoh0".into(),
            mode: ZenohMode::Client,
            connect: vec!["tcp/10.0.0.1:7447".into(), "tls/gs.example.org:7447".into()],
            listen: vec![],
            config_file: Some("/etc/usal/z.json5".into()),
            heartbeat: ms(1000),
            lease: ms(60_000),
        })]
    );
    let c = parse(&net(
        r#"<zenoh name="wan" mode="peer" listen="tcp/0.0.0.0:7448" heartbeatMs="500"/>"#,
    ))
    .unwrap();
    let [LinkConfig::Zenoh(z)] = c.links.as_slice() else {
        panic!("{:?}", c.links);
    };
    assert_eq!(
        (z.mode, z.listen.as_slice()),
        (ZenohMode::Peer, &["tcp/0.0.0.0:7448".to_owned()][..])
    );
    assert_eq!((z.heartbeat, z.lease), (ms(500), ms(30_000)));
}

#[test]
fn a_zenoh_link_that_cannot_work_is_refused_where_it_is_written() {
    let (text, line, column) = message(&net("  <zenoh/>"));
    assert_eq!((line, column), (2, 3));
    assert!(
        text.contains("<zenoh>: missing required attribute connect")
            && text.contains("the router a client reaches the others through"),
        "{text}"
    );
    let (text, ..) = message(&net(
        r#"<zenoh connect="tcp/10.0.0.1:7447" listen="tcp/0.0.0.0:7447"/>"#,
    ));
    assert!(
        text.contains("attribute listen") && text.contains("a client only connects"),
        "{text}"
    );
    let (text, ..) = message(&net(r#"<zenoh connect="10.0.0.1:7447"/>"#));
    assert!(
        text.contains("attribute connect") && text.contains("protocol/address"),
        "{text}"
    );
    let (text, ..) = message(&net(r#"<zenoh mode="router" connect="tcp/a:1"/>"#));
    assert!(
        text.contains("attribute mode") && text.contains("`client`"),
        "{text}"
    );
    let (text, ..) = message(&net(r#"<zenoh connect=" , "/>"#));
    assert!(text.contains("attribute connect"), "{text}");
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
    let (text, line, column) = message("<?xml version=\"1.0\"?>\n<!-- x -->\n<netwrk node=\"a\"/>");
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
            "config/network.xml:2:1: <network>: unknown element <radio>; expected <ethernet>, <shm>, <serial>, <serialduo>, <zenoh>, <security>, <access>"
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
    assert!(
        text.ends_with(
            "missing required attribute addressRx (a serial port path like /dev/ttyUSB0 or COM3)"
        ),
        "{text}"
    );
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
            (r#"<shm maxPeers="many"/>"#, "attribute maxPeers: expected an integer from 1 to 1024 (peers), found \"many\""),
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
        (
            r#"<serial address="a" MaxPacketSize="70000"/>"#,
            "MaxPacketSize: 70000 is out of range, expected 32 to 65535 bytes",
        ),
        (
            r#"<serial address="a" baudRate="0"/>"#,
            "baudRate: 0 is out of range, expected 50 to 12000000 bits per second",
        ),
        (
            r#"<serialduo addressTx="a" addressRx="b" baudRateRx="0"/>"#,
            "baudRateRx: 0 is out of range, expected 50 to 12000000 bits per second",
        ),
        (
            r#"<serial address="a" MaxMessageQueue="0"/>"#,
            "MaxMessageQueue: 0 is out of range, expected 1 to 65536 messages",
        ),
        (
            r#"<serial address="a" TimeToResend="0"/>"#,
            "TimeToResend: 0 is out of range, expected 1 to 600000 milliseconds",
        ),
        (
            r#"<shm maxPeers="0"/>"#,
            "maxPeers: 0 is out of range, expected 1 to 1024 peers",
        ),
        (
            r#"<ethernet ttl="256"/>"#,
            "ttl: 256 is out of range, expected 0 to 255 hops",
        ),
        (
            r#"<ethernet heartbeatMs="0"/>"#,
            "heartbeatMs: 0 is out of range, expected 1 to 3600000 milliseconds",
        ),
        (
            r#"<shm leaseMs="99999999999999999999999"/>"#,
            "leaseMs: 99999999999999999999999 is out of range, expected 1 to 86400000 milliseconds",
        ),
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
    let (text, line, column) = message(&net(r#"<ethernet heartbeatMs="1000" leaseMs="1000"/>"#));
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
        (any::<usize>(), 0..8_usize, fragment).prop_map(|(at, len, s)| Edit::Replace(at, len, s)),
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

#[test]
fn access_rules_are_parsed_in_order() {
    let c = parse(&net(r#"<ethernet/>
<access>
  <allow kind="call" item="rover1/vas/*" from="ground/*"/>
  <allow kind="publish" item="rover1/vas/manual_control" from="ground/fmo"/>
  <allow kind="gateway" from="relay"/>
  <deny kind="file"/>
</access>"#))
    .unwrap();
    let a = c.access.expect("access parsed");
    assert_eq!(
        a.rules,
        vec![
            AccessRule {
                kind: AccessKind::Call,
                item: "rover1/vas/*".into(),
                from: "ground/*".into(),
            },
            AccessRule {
                kind: AccessKind::Publish,
                item: "rover1/vas/manual_control".into(),
                from: "ground/fmo".into(),
            },
            AccessRule {
                kind: AccessKind::Gateway,
                item: "**".into(),
                from: "relay".into(),
            },
        ]
    );
    assert_eq!(a.closed, vec![AccessKind::File]);
    assert!(!a.allows(AccessKind::File, "rover1/fpma/plans", "ground/fpmo"));
    assert!(!a.trust_claims, "claims are trusted only when said so");
    assert!(parse(&net("<ethernet/>")).unwrap().access.is_none());
    let trusting = parse(&net(r#"<ethernet/><access trustClaims="yes"/>"#)).unwrap();
    assert!(trusting.access.is_some_and(|a| a.trust_claims));
    let (msg, line, _) = message(&net("<ethernet/>\n<access trustClaims=\"maybe\"/>"));
    assert_eq!(line, 3, "{msg}");
    assert!(
        msg.contains("trustClaims") && msg.contains("yes or no"),
        "{msg}"
    );
}

#[test]
fn access_errors_name_line_and_column() {
    let (msg, line, column) = message(&net(
        "<ethernet/>\n<access>\n  <allow kind=\"cal\" from=\"x\"/>\n</access>",
    ));
    assert_eq!((line, column), (4, 10), "{msg}");
    assert!(msg.contains("one of call, file, publish, gateway"), "{msg}");
    let (msg, line, column) = message(&net(
        "<ethernet/>\n<access>\n  <allow kind=\"call\" item=\"a//b\" from=\"x\"/>\n</access>",
    ));
    assert_eq!((line, column), (4, 22), "{msg}");
    assert!(msg.contains("name pattern"), "{msg}");
    let (msg, line, _) = message(&net(
        "<ethernet/>\n<access>\n  <allow kind=\"call\"/>\n</access>",
    ));
    assert_eq!(line, 4, "{msg}");
    assert!(msg.contains("from"), "{msg}");
    let (msg, line, column) = message(&net("<ethernet/>\n<access/>\n<access/>"));
    assert_eq!((line, column), (4, 1), "{msg}");
    assert!(msg.contains("only once"), "{msg}");
    let (msg, line, _) = message(&net(
        "<ethernet/>\n<access>\n  <permit kind=\"call\"/>\n</access>",
    ));
    assert_eq!(line, 4, "{msg}");
    assert!(msg.contains("permit"), "{msg}");
}

// ---- <security> (link authentication) -----------------------------------------------------

#[test]
fn security_key_file_is_relative_to_the_xml_file() {
    let text = net(r#"<security keyFile="keys/domain.key"/><ethernet/>"#);
    let c = NetworkConfig::parse(&text, Some(Path::new("/etc/usal/network.xml"))).unwrap();
    assert_eq!(
        c.security,
        Some(SecurityConfig {
            key_file: "/etc/usal/keys/domain.key".into(),
            encrypt_radio: false,
            identity_file: None,
            identities: None,
        })
    );
    let text = net(
        r#"<security keyFile="d.key" identityFile="vas.id" identities="/r/ids.xml"/><ethernet/>"#,
    );
    let c = NetworkConfig::parse(&text, Some(Path::new("/etc/usal/network.xml"))).unwrap();
    let s = c.security.unwrap();
    assert_eq!(
        s.identity_file.as_deref(),
        Some(Path::new("/etc/usal/vas.id"))
    );
    assert_eq!(s.identities.as_deref(), Some(Path::new("/r/ids.xml")));
    let text = net(r#"<ethernet/><security keyFile="/k/d.key" encrypt="radio"/>"#);
    let c = NetworkConfig::parse(&text, Some(Path::new("network.xml"))).unwrap();
    let s = c.security.unwrap();
    assert_eq!(s.key_file, Path::new("/k/d.key"));
    assert!(s.encrypt_radio);
    assert_eq!(c.links.len(), 1, "<security> is not a link");
    let c = parse(&net(
        r#"<ethernet/><security keyFile="d.key" encrypt="none"/>"#,
    ))
    .unwrap();
    assert_eq!(c.security.unwrap().key_file, Path::new("d.key"));
    assert_eq!(parse(&net("<ethernet/>")).unwrap().security, None);
}

#[test]
fn security_errors_have_line_and_column() {
    let (text, line, column) = message(&net("<ethernet/>\n  <security/>"));
    assert_eq!((line, column), (3, 3));
    assert!(
        text.contains("<security>") && text.contains("keyFile"),
        "{text}"
    );
    let (text, line, column) = message(&net(r#"<security keyFile="k" encrypt="all"/><ethernet/>"#));
    assert_eq!((line, column), (2, 23));
    assert!(
        text.contains("encrypt") && text.contains("`radio`"),
        "{text}"
    );
    let (text, line, column) = message(&net(r#"<security keyFile=" "/><ethernet/>"#));
    assert_eq!((line, column), (2, 11));
    assert!(text.contains("usal keygen"), "{text}");
    let (text, line, column) = message(&net(r#"<security keyfile="k"/><ethernet/>"#));
    assert_eq!((line, column), (2, 11));
    assert!(text.contains("keyFile"), "{text}");
    let (text, line, column) = message(&net(
        "<security keyFile=\"a\"/>\n<security keyFile=\"b\"/><ethernet/>",
    ));
    assert_eq!((line, column), (3, 1));
    assert!(
        text.contains("second <security>") && text.contains("line 2, column 1"),
        "{text}"
    );
    let (text, ..) = message(&net(
        r#"<security keyFile="k"><peer/></security><ethernet/>"#,
    ));
    assert!(text.contains("no child elements"), "{text}");
    let (text, ..) = message(&net(r#"<securty keyFile="k"/><ethernet/>"#));
    assert!(text.contains("did you mean <security>"), "{text}");
}

#[test]
fn a_service_started_by_a_launcher_takes_its_node_domain_and_namespace_from_the_environment() {
    let none = NetworkConfig::from_vars("hello", |_| None).unwrap();
    assert_eq!(none.node, "hello");
    assert_eq!(none.domain, DEFAULT_DOMAIN);
    assert_eq!(none.namespace, None);
    let launched = NetworkConfig::from_vars("hello", |name| {
        Some(
            match name {
                env::NODE => "air-hello",
                env::DOMAIN => "rover-demo-42",
                env::NAMESPACE => "rover1",
                _ => return None,
            }
            .into(),
        )
    })
    .unwrap();
    assert_eq!(
        (
            launched.node.as_str(),
            launched.domain.as_str(),
            launched.namespace.as_deref()
        ),
        ("air-hello", "rover-demo-42", Some("rover1"))
    );
    // A network file named there is read, and an unreadable one says which.
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("net.xml");
    std::fs::write(&file, EXAMPLE).unwrap();
    let from_file = NetworkConfig::from_vars("hello", |name| {
        (name == env::NETWORK).then(|| file.clone().into_os_string())
    })
    .unwrap();
    assert_eq!(from_file.node, "air");
    assert_eq!(from_file.namespace.as_deref(), Some("rover1"));
    let missing = dir.path().join("absent.xml");
    let e = NetworkConfig::from_vars("hello", |name| {
        (name == env::NETWORK).then(|| missing.clone().into_os_string())
    })
    .unwrap_err();
    assert!(e.to_string().contains("absent.xml"), "{e}");
}
