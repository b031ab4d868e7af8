//! Owned names and access control, over real sockets and processes.
//!
//! The attacker of the first two tests is a plain UDP socket speaking the wire protocol by
//! hand (what anyone on the LAN can do); the victims are real nodes. The `<access>` tests run
//! every node as a `marea-probe` child process, the protected one from a `network.xml` with an
//! `<access>` element.

mod common;

use std::net::{SocketAddr, UdpSocket};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use common::{probe_with_config, Net, Proc, T};
use marea::codec::{decode_message, encode_message};
use marea::config::{EthernetConfig, LinkConfig};
use marea::link::datagram::{self, Datagram, DatagramWriter, Entry};
use marea::protocol::{Declaration, ItemKind, LoggedDeclaration, Message, NodeId, Origin};
use marea::typeinfo::TypeInfo;
use marea::{NetworkConfig, Node};

/// An in-process node on loopback, in the test's own domain and multicast port.
fn cfg(net: &Net, node: &str, namespace: &str) -> NetworkConfig {
    let mut c = NetworkConfig::ethernet_loopback(node);
    c.namespace = Some(namespace.to_owned());
    c.domain = net.domain.clone();
    c.links = vec![LinkConfig::Ethernet(EthernetConfig {
        interface: std::net::Ipv4Addr::LOCALHOST,
        bind: "127.0.0.1:0".parse().expect("literal"),
        multicast: std::net::SocketAddrV4::new(std::net::Ipv4Addr::new(239, 255, 77, 1), net.port),
        heartbeat: Duration::from_millis(net.heartbeat_ms),
        lease: Duration::from_millis(net.lease_ms),
        ..EthernetConfig::default()
    })];
    c
}

fn udp_addr(node: &Node) -> SocketAddr {
    node.link_addrs()[0]
        .trim_start_matches("udp://")
        .parse()
        .expect("a UDP link address")
}

/// A hand-made node: a UDP socket that says what it likes.
struct Attacker {
    sock: UdpSocket,
    id: NodeId,
    domain: String,
    seq: u32,
}

impl Attacker {
    fn new(domain: &str) -> Attacker {
        let sock = UdpSocket::bind("127.0.0.1:0").expect("bind");
        sock.set_read_timeout(Some(Duration::from_millis(100)))
            .expect("timeout");
        Attacker {
            sock,
            id: 0xbad0_0000_0000_0001,
            domain: domain.to_owned(),
            seq: 0,
        }
    }

    fn discovery(&self, to: SocketAddr, msg: &Message) {
        let d = datagram::discovery_datagram(&encode_message(msg));
        self.sock.send_to(&d, to).expect("send");
    }

    /// Introduces itself to `to` as node `evil` of namespace `evil`.
    fn hello(&self, to: SocketAddr, counter: u32) {
        self.discovery(
            to,
            &Message::Hello {
                node_id: self.id,
                domain: self.domain.clone(),
                node: "evil".into(),
                namespace: "evil".into(),
                counter,
                lease_ms: 60_000,
                gateway: false,
                asks_introduction: false,
            },
        );
    }

    /// Sends safe messages to `to` in a session of its own (a SYN before the first).
    fn safe(&mut self, to: SocketAddr, msgs: &[Message]) {
        let mut w = DatagramWriter::new(1400);
        if self.seq == 0 {
            w.push_syn(0x5eed);
        }
        for m in msgs {
            assert!(w.push_safe(self.seq, &encode_message(m)), "fits a datagram");
            self.seq += 1;
        }
        self.sock.send_to(&w.take(), to).expect("send");
    }

    fn fast(&self, to: SocketAddr, msg: &Message) {
        let mut w = DatagramWriter::new(1400);
        assert!(w.push_fast(&encode_message(msg)));
        self.sock.send_to(&w.take(), to).expect("send");
    }

    /// Says hello to `to` and reads what it answers until it introduces itself: its node id.
    fn learn_id(&self, to: SocketAddr, within: Duration) -> NodeId {
        let deadline = Instant::now() + within;
        let mut buf = vec![0u8; 65_536];
        let mut last_hello = Instant::now() - Duration::from_secs(1);
        while Instant::now() < deadline {
            if last_hello.elapsed() > Duration::from_millis(300) {
                self.hello(to, 0);
                last_hello = Instant::now();
            }
            let Ok((n, from)) = self.sock.recv_from(&mut buf) else {
                continue;
            };
            if from != to {
                continue;
            }
            let msgs: Vec<Vec<u8>> = match datagram::decode(&buf[..n]) {
                Ok(Datagram::Discovery(m)) => vec![m.to_vec()],
                Ok(Datagram::Data(entries)) => entries
                    .into_iter()
                    .filter_map(|e| match e {
                        Entry::Safe { msg, .. } | Entry::Fast(msg) => Some(msg.to_vec()),
                        _ => None,
                    })
                    .collect(),
                Err(_) => vec![],
            };
            for m in msgs {
                if let Ok(Message::Hello { node_id, .. }) = decode_message(&m) {
                    return node_id;
                }
            }
        }
        panic!("{to} never introduced itself");
    }
}

fn offer(id: u32, kind: ItemKind, name: &str, ty: TypeInfo) -> Declaration {
    Declaration::Offer {
        id,
        service: 1,
        kind,
        name: name.into(),
        ty,
        origin: None,
    }
}

#[test]
fn a_node_of_another_namespace_cannot_offer_rover1_names() {
    let net = Net::new("access-owned");
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    rt.block_on(async {
        let gs = Node::open(&cfg(&net, "gs", "ground")).await.expect("gs");
        let air = Node::open(&cfg(&net, "air", "rover1")).await.expect("air");
        let vas = air.service("vas").expect("vas");
        let position = vas.publish_variable::<u64>("position").expect("publish");
        let station = gs.service("fmo").expect("fmo");
        let sub = station
            .subscribe_variable::<u64>("rover1/vas/position")
            .expect("subscribe");
        assert!(position.wait_remote_subscribers(1, T).await);

        // The impostor: "evil" of namespace "evil" declares rover1/vas/position and the
        // function the real VAS provides, then publishes its own positions.
        let victim = udp_addr(&gs);
        let mut evil = Attacker::new(&net.domain);
        evil.hello(victim, 3);
        evil.safe(
            victim,
            &[Message::DeclBatch {
                after: 0,
                upto: 3,
                reset: false,
                entries: vec![
                    LoggedDeclaration {
                        counter: 1,
                        decl: Declaration::Service {
                            id: 1,
                            name: "vas".into(),
                        },
                    },
                    LoggedDeclaration {
                        counter: 2,
                        decl: offer(
                            2,
                            ItemKind::Variable,
                            "rover1/vas/position",
                            TypeInfo::of::<u64>(),
                        ),
                    },
                    LoggedDeclaration {
                        counter: 3,
                        decl: offer(
                            3,
                            ItemKind::Function,
                            "rover1/vas/push_waypoints",
                            TypeInfo::of::<fn(u64) -> u64>(),
                        ),
                    },
                ],
            }],
        );
        assert!(
            gs.wait_until(T, |n| n.refusals().rejected >= 2).await,
            "the impostor's offers were not refused: {:?}",
            gs.refusals()
        );
        // While the impostor keeps publishing, the subscriber hears the real VAS only.
        let attack = async {
            let payload = marea::codec::encode_payload(&999_999u64).expect("encodes");
            loop {
                evil.fast(
                    victim,
                    &Message::Var {
                        id: 2,
                        payload: payload.clone(),
                    },
                );
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
        };
        let listen = async {
            let mut from_air = 0;
            for i in 0..40u64 {
                position.set(&i).expect("set");
                let s = sub.recv_timeout(T).await.expect("a position");
                assert_eq!(s.publisher, "air", "a sample from the impostor: {s:?}");
                assert_ne!(s.value, 999_999);
                from_air += 1;
                tokio::time::sleep(Duration::from_millis(10)).await;
            }
            from_air
        };
        let from_air = tokio::select! {
            n = listen => n,
            _ = attack => unreachable!("the attack loops"),
        };
        assert_eq!(from_air, 40);
        let catalog = gs.catalog();
        let evil_items: Vec<String> = catalog
            .nodes
            .iter()
            .filter(|n| n.name == "evil")
            .flat_map(|n| n.services.iter().flat_map(|s| s.items.iter()))
            .map(|i| i.name.clone())
            .collect();
        assert!(evil_items.is_empty(), "listed: {evil_items:?}");
        // The refusals show in the link's health, as any station following it sees them.
        let health = station
            .subscribe_variable::<marea::LinkHealth>("ground/link/*/stats")
            .expect("subscribe to health");
        let counted = tokio::time::timeout(T, async {
            loop {
                let h = health.recv().await.expect("health");
                if h.value.rejected >= 2 {
                    break h.value;
                }
            }
        })
        .await
        .expect("the link health counted the refusals");
        assert_eq!(counted.denied, 0);
        drop((sub, health, station, position, vas));
        gs.shutdown().await;
        air.shutdown().await;
    });
}

#[test]
fn a_forged_bye_from_another_address_does_not_evict() {
    let net = Net::new("access-bye");
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    rt.block_on(async {
        let gs = Node::open(&cfg(&net, "gs", "ground")).await.expect("gs");
        let air = Node::open(&cfg(&net, "air", "rover1")).await.expect("air");
        let vas = air.service("vas").expect("vas");
        let _slow = vas
            .provide_function("slow", |x: u64| async move {
                tokio::time::sleep(Duration::from_millis(1500)).await;
                Ok::<u64, String>(x)
            })
            .expect("provide");
        let station = gs.service("fmo").expect("fmo");
        let slow = station
            .function::<u64, u64>("rover1/vas/slow")
            .expect("function");
        assert!(slow.wait_provider(T).await);

        let evil = Attacker::new(&net.domain);
        let air_id = evil.learn_id(udp_addr(&air), T);
        let victim = udp_addr(&gs);
        // A call in flight while the attacker says Bye for air, again and again.
        let call = slow.call(&7, Duration::from_secs(10));
        let forge = async {
            loop {
                evil.discovery(victim, &Message::Bye { node_id: air_id });
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        };
        let result = tokio::select! {
            r = call => r,
            _ = forge => unreachable!("the forging loops"),
        };
        assert_eq!(result, Ok(7), "the call failed: air was evicted");
        assert!(gs.peers().iter().any(|p| p.name == "air"));
        assert!(
            gs.refusals().rejected > 0,
            "the forged Byes were not counted"
        );
        drop((slow, station, vas));
        gs.shutdown().await;
        air.shutdown().await;
    });
}

/// A `network.xml` for a probe in the test's domain, with `access` inside `<network>`.
fn network_xml(dir: &Path, net: &Net, node: &str, namespace: &str, access: &str) -> PathBuf {
    let xml = format!(
        r#"<network node="{node}" namespace="{namespace}" domain="{domain}">
  <ethernet bind="127.0.0.1:0" multicast="239.255.77.1:{port}" interface="127.0.0.1"
            heartbeatMs="{hb}" leaseMs="{lease}"/>
  <access trustClaims="yes">
    {access}
  </access>
</network>
"#,
        domain = net.domain,
        port = net.port,
        hb = net.heartbeat_ms,
        lease = net.lease_ms,
    );
    let path = dir.join(format!("{node}.xml"));
    std::fs::write(&path, xml).expect("write network.xml");
    path
}

#[test]
fn access_denies_a_call_from_a_node_it_does_not_name() {
    let net = Net::new("access-call");
    let dir = tempfile::tempdir().expect("tempdir");
    let config = network_xml(
        dir.path(),
        &net,
        "air",
        "rover1",
        r#"<allow kind="call" item="rover1/vas/*" from="ground/*"/>"#,
    );
    let mut vas = probe_with_config("vas", &config, "vas", &[], &["provide", "--item", "retask"]);
    vas.expect_key(T, "ready");
    let call = |node: &str, ns: &str, arg: &str| {
        net.probe_ns(
            node,
            ns,
            &[
                "call",
                "--name",
                "rover1/vas/retask",
                "--arg",
                arg,
                "--wait-ms",
                "10000",
            ],
        )
    };
    let mut evil = call("fmo", "evil", "13");
    let refused = evil.expect(T, "error or ok", |v| {
        v.get("error").is_some() || v.get("ok").is_some()
    });
    assert_eq!(refused["error"], "denied", "{refused}");
    assert!(
        refused["message"]
            .as_str()
            .is_some_and(|m| m.contains("denied")),
        "{refused}"
    );
    let mut fmo = call("fmo", "ground", "21");
    let ok = fmo.expect(T, "error or ok", |v| {
        v.get("error").is_some() || v.get("ok").is_some()
    });
    assert_eq!(ok["ok"], 42, "{ok}");
    // The provider's handler ran for the allowed call only (the denied one carried 13).
    let called = vas.expect_key(T, "called");
    assert_eq!(called["called"], 21, "{called}");
}

#[test]
fn access_denies_a_file_with_the_denied_verdict() {
    let net = Net::new("access-file");
    let dir = tempfile::tempdir().expect("tempdir");
    let inbox = dir.path().join("plans");
    std::fs::create_dir_all(&inbox).expect("inbox");
    let config = network_xml(
        dir.path(),
        &net,
        "air",
        "rover1",
        r#"<allow kind="file" item="rover1/fpma/plans" from="ground/fpmo"/>"#,
    );
    let mut fpma = probe_with_config(
        "fpma",
        &config,
        "fpma",
        &[],
        &[
            "sink",
            "--item",
            "plans",
            "--dir",
            &inbox.display().to_string(),
        ],
    );
    fpma.expect_key(T, "ready");
    let plan = dir.path().join("plan.xml");
    std::fs::write(&plan, b"<plan/>").expect("plan");
    let send = |ns: &str| {
        net.probe_ns(
            "fpmo",
            ns,
            &common::sending(&plan.display().to_string(), "rover1/fpma/plans", "20"),
        )
    };
    let mut evil = send("evil");
    let refused = evil.expect(T, "error or done", |v| {
        v.get("error").is_some() || v.get("done").is_some()
    });
    assert_eq!(refused["error"], "denied", "{refused}");
    // The sink keeps its partial files in a private `.partial/` directory: nothing of the
    // denied file may be there either.
    let entries = |dir: &std::path::Path| -> Vec<String> {
        std::fs::read_dir(dir).map_or_else(
            |_| Vec::new(),
            |rd| {
                rd.filter_map(Result::ok)
                    .map(|e| e.file_name().to_string_lossy().into_owned())
                    .collect()
            },
        )
    };
    let stored: Vec<String> = entries(&inbox)
        .into_iter()
        .filter(|n| n != ".partial")
        .collect();
    assert!(
        stored.is_empty(),
        "a denied file reached the sink: {stored:?}"
    );
    let partial = entries(&inbox.join(".partial"));
    assert!(partial.is_empty(), "a denied file left a part: {partial:?}");
    let mut fpmo = send("ground");
    let done = fpmo.expect(T, "error or done", |v| {
        v.get("error").is_some() || v.get("done").is_some()
    });
    assert_eq!(done["done"], 7, "{done}");
    let received = fpma.expect_key(T, "received");
    assert_eq!(received["size"], 7);
}

#[test]
fn a_disallowed_publishers_manual_control_is_not_delivered() {
    let net = Net::new("access-publish");
    let dir = tempfile::tempdir().expect("tempdir");
    let config = network_xml(
        dir.path(),
        &net,
        "air",
        "rover1",
        r#"<allow kind="publish" item="*/fmo/manual_control" from="ground/fmo"/>"#,
    );
    let publish = |ns: &str| publish_manual(&net, ns);
    let mut fmo = publish("ground");
    let mut evil = publish("evil");
    fmo.expect_key(T, "ready");
    evil.expect_key(T, "ready");
    let mut vas = probe_with_config(
        "vas",
        &config,
        "vas",
        &[],
        &[
            "var-sub",
            "--pattern",
            "*/fmo/manual_control",
            "--count",
            "60",
        ],
    );
    let mut names = Vec::new();
    while names.len() < 60 {
        let v = vas.expect(T, "a sample", |v| v.get("name").is_some());
        names.push(v["name"].as_str().unwrap_or_default().to_owned());
    }
    assert!(
        names.iter().all(|n| n == "ground/fmo/manual_control"),
        "delivered: {names:?}"
    );
}

/// `marea-probe` publishing manual-control samples at 50 Hz as node `fmo` of `namespace`.
fn publish_manual(net: &Net, namespace: &str) -> Proc {
    net.probe_ns(
        "fmo",
        namespace,
        &[
            "--service",
            "fmo",
            "var-pub",
            "--item",
            "manual_control",
            "--count",
            "1000000",
            "--interval-ms",
            "20",
        ],
    )
}

#[test]
fn a_call_expired_while_waiting_never_runs_and_a_newer_one_supersedes_a_waiting_one() {
    let net = Net::new("access-lanes");
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    rt.block_on(async {
        let gs = Node::open(&cfg(&net, "gs", "ground")).await.expect("gs");
        let air = Node::open(&cfg(&net, "air", "rover1")).await.expect("air");
        let vas = air.service("vas").expect("vas");
        let (tx, mut ran) = tokio::sync::mpsc::unbounded_channel::<u64>();
        let _retask = vas
            .provide_function("retask", move |x: u64| {
                let tx = tx.clone();
                async move {
                    let _ = tx.send(x);
                    tokio::time::sleep(Duration::from_millis(600)).await;
                    Ok::<u64, String>(x)
                }
            })
            .expect("provide");
        let station = gs.service("fmo").expect("fmo");
        let retask = station
            .function::<u64, u64>("rover1/vas/retask")
            .expect("function");
        assert!(retask.wait_provider(T).await);
        let long = Duration::from_secs(10);
        // Each call is sent when first polled, and `join!` polls in order: they arrive in order.
        // Call 2 waits behind call 1 and its caller gives up after 300 ms: it must never run.
        let (one, two) = tokio::join!(
            retask.call(&1, long),
            retask.call(&2, Duration::from_millis(300))
        );
        assert_eq!(one, Ok(1));
        assert!(
            matches!(two, Err(marea::CallError::Timeout { .. })),
            "{two:?}"
        );
        // Call 4 waits behind call 3; call 5 arrives and replaces it: the newest wins.
        let (three, four, five) = tokio::join!(
            retask.call(&3, long),
            retask.call(&4, long),
            retask.call(&5, long)
        );
        assert_eq!((three, five), (Ok(3), Ok(5)));
        assert!(
            matches!(four, Err(marea::CallError::Superseded { .. })),
            "{four:?}"
        );
        let mut executed = Vec::new();
        while let Ok(x) = ran.try_recv() {
            executed.push(x);
        }
        assert_eq!(executed, [1, 3, 5]);
        drop((retask, station, vas));
        gs.shutdown().await;
        air.shutdown().await;
    });
}

/// A provider learns who called, as its access rules see it: the calling node's namespace
/// and name, over the network and within its own node.
#[test]
fn a_provider_learns_who_called() {
    let net = Net::new("access-caller");
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    rt.block_on(async {
        let gs = Node::open(&cfg(&net, "gs", "ground")).await.expect("gs");
        let air = Node::open(&cfg(&net, "air", "rover1")).await.expect("air");
        let vas = air.service("vas").expect("vas");
        let _who = vas
            .provide_function_with_caller("who", |(): (), caller: marea::Caller| async move {
                Ok::<String, String>(caller.to_string())
            })
            .expect("provide");
        let remote = gs
            .service("fmo")
            .expect("fmo")
            .function::<(), String>("rover1/vas/who")
            .expect("function");
        assert!(remote.wait_provider(T).await);
        assert_eq!(remote.call(&(), T).await.as_deref(), Ok("ground/gs"));
        let local = air
            .service("fpma")
            .expect("fpma")
            .function::<(), String>("rover1/vas/who")
            .expect("function");
        assert!(local.wait_provider(T).await);
        assert_eq!(local.call(&(), T).await.as_deref(), Ok("rover1/air"));
        drop((remote, local, vas));
        gs.shutdown().await;
        air.shutdown().await;
    });
}

/// `<access>` rules match the names peers announce: without a roster to prove them, a node
/// refuses to open (saying why and what to do) unless its rules say claims are trusted.
#[test]
fn access_rules_without_a_roster_refuse_to_open_unless_claims_are_trusted() {
    let net = Net::new("access-no-roster");
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    rt.block_on(async {
        let mut config = cfg(&net, "air", "rover1");
        let mut rules = marea::config::AccessConfig {
            rules: vec![marea::config::AccessRule {
                kind: marea::config::AccessKind::Call,
                item: "rover1/vas/*".into(),
                from: "ground/*".into(),
            }],
            closed: vec![],
            trust_claims: false,
        };
        config.access = Some(rules.clone());
        let e = Node::open(&config)
            .await
            .err()
            .expect("rules without a roster refused")
            .to_string();
        assert!(
            e.contains("node air") && e.contains("roster") && e.contains("trustClaims"),
            "{e}"
        );
        rules.trust_claims = true;
        config.access = Some(rules);
        let node = Node::open(&config).await.expect("claims trusted, as said");
        node.shutdown().await;
    });
}

/// Only a gateway may say whom it relays a call for. A plain node (`evil`, no gateway) sends
/// calls of every id a small node may use, each claiming to be relayed for `ground/fmo`,
/// whom the victim's `<access>` lets call: none runs, each is refused and counted, while a
/// real `ground` node's call is served.
#[test]
fn a_call_claimed_as_relayed_by_a_node_that_is_no_gateway_never_runs() {
    let net = Net::new("access-relay");
    let rt = tokio::runtime::Runtime::new().expect("runtime");
    rt.block_on(async {
        let mut config = cfg(&net, "air", "rover1");
        config.access = Some(marea::config::AccessConfig {
            rules: vec![marea::config::AccessRule {
                kind: marea::config::AccessKind::Call,
                item: "rover1/vas/*".into(),
                from: "ground/*".into(),
            }],
            closed: vec![],
            trust_claims: true,
        });
        let air = Node::open(&config).await.expect("air");
        let vas = air.service("vas").expect("vas");
        let (tx, mut ran) = tokio::sync::mpsc::unbounded_channel::<u64>();
        let _retask = vas
            .provide_function("retask", move |x: u64| {
                let _ = tx.send(x);
                async move { Ok::<u64, String>(2 * x) }
            })
            .expect("provide");

        let victim = udp_addr(&air);
        let mut evil = Attacker::new(&net.domain);
        evil.hello(victim, 0);
        let args = marea::codec::encode_payload(&13u64).expect("a u64 encodes");
        let claimed = Origin {
            node: 0x600d,
            name: "fmo".into(),
            hops: 1,
            namespace: "ground".into(),
        };
        let calls: Vec<Message> = (1..=24u32)
            .map(|id| Message::Call {
                call_id: u64::from(id),
                id,
                remaining_ms: 5_000,
                args: args.clone(),
                caller: Some(claimed.clone()),
            })
            .collect();
        for batch in calls.chunks(8) {
            evil.safe(victim, batch);
        }
        assert!(
            air.wait_until(T, |n| n.refusals().rejected >= 1).await,
            "the claimed relays were not refused: {:?}",
            air.refusals()
        );

        let gs = Node::open(&cfg(&net, "gs", "ground")).await.expect("gs");
        let station = gs.service("fmo").expect("fmo");
        let retask = station
            .function::<u64, u64>("rover1/vas/retask")
            .expect("function");
        assert!(retask.wait_provider(T).await);
        assert_eq!(retask.call(&21, T).await, Ok(42));
        assert_eq!(ran.recv().await, Some(21));
        assert!(ran.try_recv().is_err(), "a forged relayed call ran");
        drop((retask, station, vas));
        gs.shutdown().await;
        air.shutdown().await;
    });
}
