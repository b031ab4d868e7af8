//! Link authentication through the real path: `usal keygen` makes the key, `marea-probe` child
//! processes carry it (as `<security keyFile=..>` would), and what crosses UDP, a pty pair or
//! shared memory is sealed; nodes without the key, or with another, are neither discovered nor
//! delivered, and the keyed nodes' link health counts the rejections.

mod common;

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use common::attacker::Sniffer;
use common::{keygen, outcome, publishing, Net, Proc, T};
use serde_json::Value;

/// Reads link-health lines from `station` until one satisfies `pred`.
fn health_until(station: &mut Proc, what: &str, pred: impl Fn(&Value) -> bool) -> Value {
    station.expect(T, what, |v| v.get("link").is_some() && pred(v))
}

#[test]
fn keygen_refuses_to_overwrite_and_nodes_refuse_a_readable_key() {
    let dir = tempfile::tempdir().unwrap();
    let key = keygen(dir.path(), "domain.key");
    let again = Command::new(env!("CARGO_BIN_EXE_usal"))
        .args(["keygen", key.to_str().unwrap()])
        .output()
        .unwrap();
    assert!(!again.status.success());
    let err = String::from_utf8_lossy(&again.stderr);
    assert!(
        err.contains("already exists") && err.contains("domain.key"),
        "{err}"
    );

    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o644)).unwrap();
    let net = Net::new("auth_readable_key");
    let mut p = net.keyed("p", "rover1", &key, &["list", "--wait-ms", "0"]);
    let status = p.wait_exit(T);
    assert!(
        !status.success(),
        "a node must not start with a world-readable key"
    );
}

/// Variables, events and calls between two nodes with the same key over UDP.
#[test]
fn same_key_nodes_exchange_variables_events_and_calls_over_udp() {
    let dir = tempfile::tempdir().unwrap();
    let key = keygen(dir.path(), "domain.key");
    let net = Net::new("auth_udp_ok");
    let mut publ = net.keyed(
        "pub",
        "rover1",
        &key,
        &["var-pub", "--item", "position", "--count", "3"],
    );
    publ.expect_key(T, "published");
    let mut sub = net.keyed(
        "sub",
        "gs",
        &key,
        &[
            "var-sub",
            "--pattern",
            "rover1/probe/position",
            "--count",
            "1",
        ],
    );
    assert_eq!(sub.expect_key(T, "seq")["seq"], 2);

    let mut evsub = net.keyed(
        "evsub",
        "gs",
        &key,
        &["ev-sub", "--pattern", "rover1/probe/alarm", "--count", "50"],
    );
    evsub.expect_key(T, "ready");
    let mut evpub = net.keyed(
        "evpub",
        "rover1",
        &key,
        &["ev-pub", "--item", "alarm", "--count", "50"],
    );
    let done = evpub.expect_key(T, "raised");
    assert_eq!(done["acknowledged_by_all"], 50, "{done}");
    let r = evsub.expect_key(T, "received");
    assert_eq!(r["received"], 50);
    assert_eq!(r["in_order"], true);

    let mut prov = net.keyed("prov", "rover1", &key, &["provide", "--item", "double"]);
    prov.expect_key(T, "ready");
    let mut call = net.keyed(
        "call",
        "gs",
        &key,
        &[
            "call",
            "--name",
            "rover1/probe/double",
            "--arg",
            "21",
            "--wait-ms",
            "10000",
        ],
    );
    let v = outcome(&mut call);
    assert_eq!(v["ok"], 42, "{v}");
}

/// A node with another key, and one with none, see nothing of the keyed nodes and deliver
/// nothing to them; the keyed nodes count what they dropped.
#[test]
fn other_key_or_no_key_is_neither_discovered_nor_delivered() {
    let dir = tempfile::tempdir().unwrap();
    let key = keygen(dir.path(), "domain.key");
    let other = keygen(dir.path(), "other.key");
    let net = Net::new("auth_udp_intruders");
    let mut publ = net.keyed("pub", "rover1", &key, &publishing("position"));
    publ.expect_key(T, "ready");
    // The intruders publish the same name: a keyed subscriber must only ever see the keyed one.
    let mut wrong = net.keyed("wrongkey", "rover1", &other, &publishing("intruder"));
    let mut none = net.probe_ns("nokey", "rover1", &publishing("intruder"));
    wrong.expect_key(T, "ready");
    none.expect_key(T, "ready");
    let mut wrong_sub = net.keyed(
        "wrongsub",
        "gs",
        &other,
        &[
            "var-sub",
            "--pattern",
            "rover1/probe/position",
            "--count",
            "1",
        ],
    );
    let mut none_sub = net.probe_ns(
        "nonesub",
        "gs",
        &[
            "var-sub",
            "--pattern",
            "rover1/probe/position",
            "--count",
            "1",
        ],
    );
    wrong_sub.expect_key(T, "ready");
    none_sub.expect_key(T, "ready");

    // The keyed station: it gets the keyed publisher's values, and its own link health shows
    // the intruders' datagrams dropped as unauthenticated.
    let mut station = net.keyed(
        "station",
        "gs",
        &key,
        &["var-sub", "--pattern", "rover1/probe/*", "--count", "20"],
    );
    for _ in 0..20 {
        let v = station.expect_key(T, "seq");
        assert_eq!(v["name"], "rover1/probe/position", "{v}");
        assert_eq!(v["publisher"], "pub");
    }
    let mut health = net.keyed(
        "health",
        "gs",
        &key,
        &["health", "--pattern", "gs/link/**", "--count", "1000"],
    );
    let v = health_until(&mut health, "auth rejections counted", |v| {
        v["auth_rejected"].as_u64() > Some(0)
    });
    assert!(v["publisher"].is_string(), "{v}");
    // By now the intruders' subscribers have had many of the keyed publisher's values on the
    // wire (50 a second): none may have been delivered.
    assert!(
        wrong_sub
            .try_expect(Duration::from_secs(2), |v| v.get("seq").is_some())
            .is_none(),
        "a node with another key got a value: {:?}",
        wrong_sub.seen
    );
    assert!(
        none_sub
            .try_expect(Duration::from_millis(200), |v| v.get("seq").is_some())
            .is_none(),
        "a node without key got a value: {:?}",
        none_sub.seen
    );
    // And they discovered nobody keyed.
    for (name, k) in [("wrong-list", Some(&other)), ("none-list", None)] {
        let mut list = match k {
            Some(k) => net.keyed(name, "gs", k, &["list", "--wait-ms", "1500"]),
            None => net.probe_ns(name, "gs", &["list", "--wait-ms", "1500"]),
        };
        let v = list.expect_key(T, "nodes");
        let names: Vec<&str> = v["nodes"]
            .as_array()
            .unwrap()
            .iter()
            .filter_map(|n| n["name"].as_str())
            .collect();
        for keyed_node in ["pub", "station", "health"] {
            assert!(
                !names.contains(&keyed_node),
                "{name} discovered {keyed_node}: {names:?}"
            );
        }
    }
}

/// A datagram captured on the wire and sent again is dropped as a replay (counted), while the
/// legitimate traffic goes on.
#[test]
fn a_replayed_datagram_is_rejected_and_counted_while_traffic_flows() {
    let dir = tempfile::tempdir().unwrap();
    let key = keygen(dir.path(), "domain.key");
    let net = Net::new("auth_udp_replay");
    let spy = Sniffer::join(net.group()).expect("join the group");
    let mut publ = net.keyed("pub", "rover1", &key, &publishing("position"));
    publ.expect_key(T, "ready");
    let mut health = net.keyed(
        "victim",
        "gs",
        &key,
        &["health", "--pattern", "gs/link/**", "--count", "1000"],
    );
    health.expect_key(T, "ready");
    let mut sub = net.keyed(
        "sub",
        "gs",
        &key,
        &[
            "var-sub",
            "--pattern",
            "rover1/probe/position",
            "--count",
            "0",
        ],
    );
    sub.expect_key(T, "seq");

    // Capture what the nodes multicast (hellos and heartbeats, sealed), and who sends it.
    let mut captured: Vec<(Vec<u8>, SocketAddr)> = Vec::new();
    let deadline = Instant::now() + T;
    while captured.len() < 12 && Instant::now() < deadline {
        if let Some((d, from)) = spy.recv() {
            assert_eq!(d[0], 0xA4, "a keyed node's discovery datagram is sealed");
            captured.push((d, from));
        }
    }
    assert!(captured.len() >= 12, "captured only {}", captured.len());
    let senders: Vec<SocketAddr> = {
        let mut s: Vec<SocketAddr> = captured.iter().map(|(_, f)| *f).collect();
        s.sort();
        s.dedup();
        s
    };
    // Replay each, to the group and to every node's own address.
    let group = SocketAddr::V4(net.group());
    for _ in 0..3 {
        for (d, _) in &captured {
            spy.send_to(d, group).unwrap();
            for s in &senders {
                spy.send_to(d, *s).unwrap();
            }
        }
    }
    let v = health_until(&mut health, "replays counted", |v| {
        v["replay_rejected"].as_u64() > Some(0)
    });
    assert_eq!(v["auth_rejected"], 0, "nothing here was forged: {v}");
    // Legitimate traffic still flows after the replays.
    let last = sub.expect_key(T, "seq")["seq"].as_u64().unwrap();
    let later = sub.expect(T, "newer values", |v| v["seq"].as_u64() > Some(last + 10));
    assert_eq!(later["publisher"], "pub");
}

// ---- serial (pty pairs through the radio emulator) -----------------------------------------

fn runtime() -> tokio::runtime::Runtime {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .expect("runtime")
}

/// A node on one end of the radio; `security` is a `<security ../>` element or empty.
fn radio_config(node: &str, domain: &str, dev: &str, security: &str) -> marea::NetworkConfig {
    let xml = format!(
        r#"<network node="{node}" namespace="{node}" domain="{domain}">
  <serial name="radio" address="{dev}" baudRate="115200" heartbeatMs="300" leaseMs="3000" TimeToResend="500"/>
  {security}
</network>"#
    );
    marea::NetworkConfig::parse(&xml, None).expect("valid config")
}

fn security_element(key: &Path, encrypt: bool) -> String {
    format!(
        r#"<security keyFile="{}" encrypt="{}"/>"#,
        key.display(),
        if encrypt { "radio" } else { "none" }
    )
}

/// Polls `pred` (link counters have no change notification) until it holds or `timeout`.
async fn poll(timeout: Duration, mut pred: impl FnMut() -> bool) -> bool {
    let deadline = Instant::now() + timeout;
    while !pred() {
        if Instant::now() >= deadline {
            return false;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    true
}

fn radio_link(node: &marea::Node) -> marea::link::LinkStats {
    node.link_stats()
        .into_iter()
        .find(|(n, _)| n == "radio")
        .map(|(_, s)| s)
        .expect("the radio link")
}

/// Variables, events and calls across a real pty pair with the same key on both ends.
fn same_key_over_a_radio(encrypt: bool) {
    let dir = tempfile::tempdir().unwrap();
    let key = keygen(dir.path(), "domain.key");
    let radio = common::Radio::start(&["--seed", "5"]);
    let domain = format!("auth-radio-{encrypt}-{}", std::process::id());
    let sec = security_element(&key, encrypt);
    let air_cfg = radio_config("air", &domain, &radio.air, &sec);
    let ground_cfg = radio_config("ground", &domain, &radio.ground, &sec);
    runtime().block_on(async move {
        tokio::time::timeout(Duration::from_secs(90), async move {
            let air = marea::Node::open(&air_cfg).await.expect("air node");
            let ground = marea::Node::open(&ground_cfg).await.expect("ground node");
            let vas = air.service("vas").unwrap();
            let position = vas
                .publish_variable::<(f64, f64, f64, f32, f32)>("position")
                .unwrap();
            let alarms = vas.publish_event::<u64>("alarm").unwrap();
            let _double = vas
                .provide_function("double", |x: u64| async move { Ok::<u64, String>(x * 2) })
                .unwrap();
            let fmo = ground.service("fmo").unwrap();
            let pos_sub = fmo
                .subscribe_variable::<(f64, f64, f64, f32, f32)>("air/vas/position")
                .unwrap();
            let ev_sub = fmo.subscribe_event::<u64>("air/vas/alarm").unwrap();
            let double = fmo.function::<u64, u64>("air/vas/double").unwrap();
            assert!(
                alarms
                    .wait_remote_subscribers(1, Duration::from_secs(30))
                    .await
            );
            assert!(double.wait_provider(Duration::from_secs(30)).await);
            position.set(&(41.2, 1.9, 12.5, 90.0, 1.5)).unwrap();
            let p = tokio::time::timeout(Duration::from_secs(10), pos_sub.recv())
                .await
                .expect("a position within 10 s")
                .unwrap();
            assert_eq!(p.value, (41.2, 1.9, 12.5, 90.0, 1.5));
            for i in 0..20u64 {
                assert!(alarms.raise(&i).await.unwrap().all_acknowledged());
            }
            for i in 0..20u64 {
                let e = tokio::time::timeout(Duration::from_secs(10), ev_sub.recv())
                    .await
                    .expect("events keep coming")
                    .unwrap();
                assert_eq!(e.value, i);
            }
            assert_eq!(double.call(&21, Duration::from_secs(10)).await.unwrap(), 42);
            let s = radio_link(&ground);
            assert_eq!((s.auth_rejected, s.replay_rejected), (0, 0), "{s:?}");
            ground.shutdown().await;
            air.shutdown().await;
        })
        .await
        .expect("test took too long")
    });
}

#[test]
fn same_key_nodes_exchange_variables_events_and_calls_over_a_radio() {
    same_key_over_a_radio(false);
}

#[test]
fn same_key_nodes_exchange_over_an_encrypted_radio() {
    same_key_over_a_radio(true);
}

/// A keyed node and a node without the key (then one with another key) on the two ends of a
/// radio: neither discovers the other, nothing is delivered, the keyed node counts rejections.
#[test]
fn no_key_or_another_key_on_the_radio_is_neither_discovered_nor_delivered() {
    let dir = tempfile::tempdir().unwrap();
    let key = keygen(dir.path(), "domain.key");
    let other = keygen(dir.path(), "other.key");
    for (case, intruder_sec) in [
        ("none", String::new()),
        ("other", security_element(&other, false)),
    ] {
        let radio = common::Radio::start(&["--seed", "6"]);
        let domain = format!("auth-radio-intruder-{case}-{}", std::process::id());
        let air_cfg = radio_config("air", &domain, &radio.air, &security_element(&key, false));
        let intruder_cfg = radio_config("ground", &domain, &radio.ground, &intruder_sec);
        runtime().block_on(async move {
            tokio::time::timeout(Duration::from_secs(60), async move {
                let air = marea::Node::open(&air_cfg).await.expect("air node");
                let intruder = marea::Node::open(&intruder_cfg).await.expect("intruder");
                let vas = air.service("vas").unwrap();
                let position = vas.publish_variable::<u64>("position").unwrap();
                let got = intruder
                    .service("fmo")
                    .unwrap()
                    .subscribe_variable::<u64>("air/vas/position")
                    .unwrap();
                let _theirs = intruder
                    .service("fmo")
                    .unwrap()
                    .publish_variable::<u64>("command")
                    .unwrap();
                // The intruder's hellos and heartbeats reach the keyed node and are dropped.
                assert!(
                    poll(Duration::from_secs(20), || radio_link(&air).auth_rejected
                        >= 3)
                    .await,
                    "{case}: {:?}",
                    radio_link(&air)
                );
                // Meanwhile the keyed node's hellos and heartbeats (and values) reached the
                // intruder, which discovered nothing and got nothing.
                for i in 0..5 {
                    position.set(&i).unwrap();
                }
                assert!(
                    poll(Duration::from_secs(5), || {
                        let s = radio_link(&intruder);
                        s.corrupt + s.auth_rejected >= 3
                    })
                    .await,
                    "{case}: the intruder saw none of the keyed frames: {:?}",
                    radio_link(&intruder)
                );
                assert!(air.peers().is_empty(), "{case}: {:?}", air.peers());
                assert!(
                    intruder.peers().is_empty(),
                    "{case}: {:?}",
                    intruder.peers()
                );
                assert!(
                    tokio::time::timeout(Duration::from_millis(500), got.recv())
                        .await
                        .is_err(),
                    "{case}: the intruder got a value"
                );
                intruder.shutdown().await;
                air.shutdown().await;
            })
            .await
            .expect("test took too long")
        });
    }
}

// ---- shared memory --------------------------------------------------------------------------

fn shm_config(node: &str, service: &str, security: &str) -> marea::NetworkConfig {
    let xml = format!(
        r#"<network node="{node}" namespace="{node}">
  <shm name="local" service="{service}" heartbeatMs="200" leaseMs="1500"/>
  {security}
</network>"#
    );
    marea::NetworkConfig::parse(&xml, None).expect("valid config")
}

fn shm_link(node: &marea::Node) -> marea::link::LinkStats {
    node.link_stats()
        .into_iter()
        .find(|(n, _)| n == "local")
        .map(|(_, s)| s)
        .expect("the shm link")
}

/// Same key over shared memory: variables, events (small and large enough for the bulk inbox)
/// and calls; a node with another key, and one without a key, on the same service are neither
/// discovered nor delivered, and the nodes count what they dropped.
#[test]
fn shared_memory_with_a_key_delivers_and_refuses_another_key_or_none() {
    let dir = tempfile::tempdir().unwrap();
    let key = keygen(dir.path(), "domain.key");
    let other = keygen(dir.path(), "other.key");
    let service = format!("auth{}", std::process::id());
    let sec = security_element(&key, false);
    let a_cfg = shm_config("vehicle", &service, &sec);
    let b_cfg = shm_config("station", &service, &sec);
    let x_cfg = shm_config("intruder", &service, &security_element(&other, false));
    let y_cfg = shm_config("nokey", &service, "");
    runtime().block_on(async move {
        tokio::time::timeout(Duration::from_secs(60), async move {
            let a = marea::Node::open(&a_cfg).await.expect("vehicle");
            let b = marea::Node::open(&b_cfg).await.expect("station");
            let x = marea::Node::open(&x_cfg).await.expect("intruder");
            let y = marea::Node::open(&y_cfg).await.expect("node without key");
            let y_spied = y
                .service("fmo")
                .unwrap()
                .subscribe_variable::<u64>("vehicle/vas/position")
                .unwrap();
            let vas = a.service("vas").unwrap();
            let position = vas.publish_variable::<u64>("position").unwrap();
            let blobs = vas.publish_event::<Vec<u8>>("blob").unwrap();
            let _double = vas
                .provide_function("double", |x: u64| async move { Ok::<u64, String>(x * 2) })
                .unwrap();
            let fmo = b.service("fmo").unwrap();
            let pos = fmo
                .subscribe_variable::<u64>("vehicle/vas/position")
                .unwrap();
            let blob_sub = fmo.subscribe_event::<Vec<u8>>("vehicle/vas/blob").unwrap();
            let double = fmo.function::<u64, u64>("vehicle/vas/double").unwrap();
            let spy = x.service("fmo").unwrap();
            let spied = spy
                .subscribe_variable::<u64>("vehicle/vas/position")
                .unwrap();
            assert!(
                blobs
                    .wait_remote_subscribers(1, Duration::from_secs(20))
                    .await
            );
            assert!(double.wait_provider(Duration::from_secs(20)).await);
            position.set(&7).unwrap();
            let v = tokio::time::timeout(Duration::from_secs(10), pos.recv())
                .await
                .expect("a value")
                .unwrap();
            assert_eq!(v.value, 7);
            let big: Vec<u8> = (0..600_000u32).map(|i| (i * 7) as u8).collect();
            for blob in [vec![1u8, 2, 3], big.clone()] {
                assert!(blobs.raise(&blob).await.unwrap().all_acknowledged());
                let e = tokio::time::timeout(Duration::from_secs(10), blob_sub.recv())
                    .await
                    .expect("an event")
                    .unwrap();
                assert_eq!(e.value, blob);
            }
            assert_eq!(double.call(&21, Duration::from_secs(5)).await.unwrap(), 42);
            // The intruder's announcements reached the keyed nodes and were dropped.
            assert!(
                poll(Duration::from_secs(10), || shm_link(&a).auth_rejected > 0).await,
                "{:?}",
                shm_link(&a)
            );
            let names = |n: &marea::Node| -> Vec<String> {
                n.peers().into_iter().map(|p| p.name).collect()
            };
            // Both intruders' announcements were dropped: the one without a key as unsealed.
            assert!(
                poll(Duration::from_secs(10), || shm_link(&a).auth_rejected >= 2).await,
                "{:?}",
                shm_link(&a)
            );
            // And the node without a key drops the keyed frames as unreadable.
            assert!(
                poll(Duration::from_secs(10), || shm_link(&y).corrupt > 0).await,
                "{:?}",
                shm_link(&y)
            );
            assert_eq!(names(&a), vec!["station".to_owned()]);
            assert!(names(&x).is_empty(), "{:?}", names(&x));
            assert!(
                names(&y).is_empty(),
                "the node without a key discovered a keyed node: {:?}",
                names(&y)
            );
            assert!(
                tokio::time::timeout(Duration::from_millis(300), spied.recv())
                    .await
                    .is_err(),
                "the intruder got a value"
            );
            assert!(
                tokio::time::timeout(Duration::from_millis(100), y_spied.recv())
                    .await
                    .is_err(),
                "the node without a key got a value"
            );
            y.shutdown().await;
            x.shutdown().await;
            b.shutdown().await;
            a.shutdown().await;
        })
        .await
        .expect("test took too long")
    });
}

// ---- stage 2: per-node identity keys -------------------------------------------------------

/// `usal keygen --identity`: the secret (0600) and the public key file.
fn identity_keygen(dir: &Path, name: &str) -> (PathBuf, String) {
    let path = dir.join(name);
    let out = Command::new(env!("CARGO_BIN_EXE_usal"))
        .args(["keygen", "--identity", path.to_str().unwrap()])
        .output()
        .expect("run usal keygen --identity");
    assert!(out.status.success(), "{out:?}");
    let public = std::fs::read_to_string(dir.join(format!("{name}.pub"))).unwrap();
    (path, public.trim().to_owned())
}

/// With a roster, a peer's declarations count only once its identity key proved to be listed
/// for its namespace: an impostor claiming `rover1` with a key listed for `rover2`, and a node
/// without identity, are heard but nothing they declare is taken; the peer record says which
/// namespaces each peer is authenticated for.
#[test]
fn identity_keys_bind_namespaces() {
    let dir = tempfile::tempdir().unwrap();
    let key = keygen(dir.path(), "domain.key");
    let (vehicle_id, vehicle_pub) = identity_keygen(dir.path(), "vehicle.id");
    let (station_id, station_pub) = identity_keygen(dir.path(), "station.id");
    let (impostor_id, impostor_pub) = identity_keygen(dir.path(), "impostor.id");
    let roster = dir.path().join("identities.xml");
    std::fs::write(
        &roster,
        format!(
            r#"<identities>
  <identity key="{vehicle_pub}" namespaces="rover1"/>
  <identity key="{station_pub}" namespaces="*"/>
  <identity key="{impostor_pub}" namespaces="rover2"/>
</identities>"#
        ),
    )
    .unwrap();
    let net = Net::new("auth_identities");
    let cfg = |node: &str, ns: &str, id: Option<&Path>| {
        let identity = id
            .map(|p| format!(r#"identityFile="{}""#, p.display()))
            .unwrap_or_default();
        let xml = format!(
            r#"<network node="{node}" namespace="{ns}" domain="{}">
  <ethernet bind="127.0.0.1:0" interface="127.0.0.1" multicast="239.255.77.1:{}" heartbeatMs="200" leaseMs="1200"/>
  <security keyFile="{}" {identity} identities="{}"/>
</network>"#,
            net.domain,
            net.port,
            key.display(),
            roster.display()
        );
        marea::NetworkConfig::parse(&xml, None).expect("valid config")
    };
    let vehicle_cfg = cfg("vehicle", "rover1", Some(&vehicle_id));
    let station_cfg = cfg("station", "gs", Some(&station_id));
    let impostor_cfg = cfg("impostor", "rover1", Some(&impostor_id));
    let anonymous_cfg = cfg("anonymous", "rover1", None);
    runtime().block_on(async move {
        tokio::time::timeout(Duration::from_secs(60), async move {
            let vehicle = marea::Node::open(&vehicle_cfg).await.expect("vehicle");
            let impostor = marea::Node::open(&impostor_cfg).await.expect("impostor");
            let anonymous = marea::Node::open(&anonymous_cfg).await.expect("anonymous");
            let _real = vehicle
                .service("vas")
                .unwrap()
                .publish_variable::<u64>("position")
                .unwrap();
            let _fake = impostor
                .service("vas")
                .unwrap()
                .publish_variable::<u64>("shadow")
                .unwrap();
            let _anon = anonymous
                .service("vas")
                .unwrap()
                .publish_variable::<u64>("ghost")
                .unwrap();
            let station = marea::Node::open(&station_cfg).await.expect("station");
            let authenticated = |n: &marea::Node, peer: &str| {
                n.peers()
                    .into_iter()
                    .find(|p| p.name == peer)
                    .and_then(|p| p.authenticated_namespaces)
            };
            assert!(
                station
                    .wait_until(Duration::from_secs(20), |n| {
                        n.is_offered(marea::protocol::ItemKind::Variable, "rover1/vas/position")
                            && authenticated(n, "impostor").is_some_and(|a| !a.is_empty())
                            && n.peers().iter().any(|p| p.name == "anonymous")
                    })
                    .await,
                "{:?}",
                station.peers()
            );
            assert_eq!(
                authenticated(&station, "vehicle"),
                Some(vec!["rover1".to_owned()])
            );
            assert_eq!(
                authenticated(&station, "impostor"),
                Some(vec!["rover2".to_owned()])
            );
            assert_eq!(authenticated(&station, "anonymous"), Some(vec![]));
            // The vehicle's declarations (which came after its proof) are taken; nothing the
            // impostor or the anonymous node declared is.
            let offered = |n: &marea::Node, name: &str| {
                n.is_offered(marea::protocol::ItemKind::Variable, name)
            };
            // (A negative: bounded, after five of their heartbeats have come and gone.)
            assert!(
                !station
                    .wait_until(Duration::from_secs(1), |n| offered(n, "rover1/vas/shadow")
                        || offered(n, "rover1/vas/ghost"))
                    .await,
                "an unauthenticated declaration was taken"
            );
            // The vehicle sees the station authenticated for any namespace.
            assert!(
                vehicle
                    .wait_until(Duration::from_secs(10), |n| {
                        authenticated(n, "station") == Some(vec!["*".to_owned()])
                    })
                    .await
            );
            for n in [station, anonymous, impostor, vehicle] {
                n.shutdown().await;
            }
        })
        .await
        .expect("test took too long")
    });
}

/// Two keyed LANs joined over an encrypted radio by keyed gateways (every node a process): a
/// value published on the air LAN reaches a subscriber on the ground LAN through both
/// gateways, every hop sealed.
#[test]
fn keyed_gateways_join_two_lans_over_an_encrypted_radio() {
    let dir = tempfile::tempdir().unwrap();
    let key = keygen(dir.path(), "domain.key");
    let ground = Net::new("auth_gateways");
    let air = Net {
        domain: ground.domain.clone(),
        port: ground.port.wrapping_add(1),
        heartbeat_ms: ground.heartbeat_ms,
        lease_ms: ground.lease_ms,
    };
    let radio = common::Radio::start(&["--seed", "9"]);
    let gateway = |net: &Net, node: &str, ns: &str, tty: &str| {
        let xml = format!(
            r#"<network node="{node}" namespace="{ns}" domain="{}">
  <ethernet name="lan" bind="127.0.0.1:0" multicast="239.255.77.1:{}" interface="127.0.0.1"
            heartbeatMs="200" leaseMs="1500"/>
  <serial name="radio" address="{tty}" baudRate="115200" heartbeatMs="500" leaseMs="5000"/>
  <security keyFile="domain.key" encrypt="radio"/>
</network>"#,
            net.domain, net.port
        );
        // keyFile is relative: resolved against this file's directory.
        let path = dir.path().join(format!("{node}.xml"));
        std::fs::write(&path, xml).unwrap();
        Proc::spawn(
            node,
            env!("CARGO_BIN_EXE_marea-probe"),
            &[
                "--config".to_owned(),
                path.display().to_string(),
                "gateway".to_owned(),
            ],
        )
    };
    let mut air_gw = gateway(&air, "air-gw", "rover1", &radio.air);
    let mut ground_gw = gateway(&ground, "ground-gw", "ground", &radio.ground);
    air_gw.expect_key(T, "ready");
    ground_gw.expect_key(T, "ready");
    let mut publ = air.keyed(
        "position",
        "rover1",
        &key,
        &["var-pub", "--item", "position", "--count", "1"],
    );
    publ.expect_key(T, "published");
    let mut monitor = ground.keyed(
        "monitor",
        "ground",
        &key,
        &["var-sub", "--pattern", "rover1/**", "--count", "1"],
    );
    let v = monitor.expect_key(Duration::from_secs(60), "seq");
    assert_eq!(v["name"], "rover1/probe/position", "{v}");
    assert_eq!(v["publisher"], "position");
}

/// A proof is an answer to one challenge: a domain-key holder that obtains a genuine proof of
/// the station (by challenging it itself) and replays it to a vehicle, under the station's id
/// once the station left, is not authenticated; the refusal is counted, and nothing it declares
/// is taken.
#[test]
fn a_replayed_identity_proof_is_refused() {
    use common::attacker::Forger;
    use marea::protocol::{Declaration, ItemKind, LoggedDeclaration, Message};

    let dir = tempfile::tempdir().unwrap();
    let key = keygen(dir.path(), "domain.key");
    let (station_id, station_pub) = identity_keygen(dir.path(), "station.id");
    let roster = dir.path().join("identities.xml");
    std::fs::write(
        &roster,
        format!(r#"<identities><identity key="{station_pub}" namespaces="ground"/></identities>"#),
    )
    .unwrap();
    let net = Net::new("auth_identity_replay");
    let inbox = dir.path().join("inbox");
    std::fs::create_dir_all(&inbox).unwrap();
    let (key_s, roster_s) = (key.to_str().unwrap(), roster.to_str().unwrap());
    let mut vehicle = net.probe_args(
        "vas",
        &[
            "--key-file",
            key_s,
            "--identities",
            roster_s,
            "--namespace",
            "rover1",
        ],
        &common::victim_cmd(&inbox),
    );
    let sniffer = Sniffer::join(net.group()).expect("join the group");
    let ready = vehicle.expect_key(T, "ready");
    let target: SocketAddr = ready["addrs"][0]
        .as_str()
        .unwrap()
        .trim_start_matches("udp://")
        .parse()
        .unwrap();
    let mut station = net.probe(
        "gs",
        &[
            "--key-file",
            key_s,
            "--identity-file",
            station_id.to_str().unwrap(),
            "--namespace",
            "ground",
            "var-pub",
            "--item",
            "position",
            "--count",
            "100000000",
            "--interval-ms",
            "20",
        ],
    );
    station.expect_key(T, "ready");
    let report = |p: &mut Proc, what: &str, pred: &dyn Fn(&Value) -> bool| -> Value {
        let v = p.expect(T, what, |v| v.get("report").is_some_and(pred));
        p.seen.clear();
        v["report"].clone()
    };
    // The station proved its key: its positions are delivered.
    let r = report(&mut vehicle, "the station authenticated", &|r| {
        r["authenticated"] == serde_json::json!(["ground/gs"])
            && r["samples"]["gs ground/probe/position"].as_u64() > Some(2)
    });
    let station_addr: SocketAddr = r["peer_addrs"]["ground/gs"]
        .as_str()
        .unwrap()
        .trim_start_matches("udp://")
        .parse()
        .unwrap();
    let (station_node_id, _) = sniffer
        .capture_from(station_addr, T)
        .expect("the station's heartbeat");
    let rejected_before = r["refusals"]["rejected"].as_u64().unwrap();

    // The spy holds the domain key: it says Hello to the station and challenges it; the
    // station answers with a genuine proof (for the spy's nonce).
    let domain_key = marea::link::auth::DomainKey::load(&key).unwrap();
    let mut spy = Forger::new(Some(&domain_key)).unwrap();
    spy.discovery(
        station_addr,
        &Message::Hello {
            node_id: 0x5b1_0000_0001,
            domain: net.domain.clone(),
            node: "spy".into(),
            namespace: "evil".into(),
            counter: 0,
            lease_ms: 60_000,
            gateway: false,
            asks_introduction: false,
        },
    )
    .unwrap();
    spy.safe(
        station_addr,
        &[Message::Challenge {
            nonce: [7; 16],
            agreement: [7; 32],
        }],
    )
    .unwrap();
    let proof = spy
        .recv_message(station_addr, T, |m| matches!(m, Message::Identity { .. }))
        .expect("the station answers a challenge");

    // The station leaves; the spy comes back to the vehicle as the station, with the proof.
    station.terminate();
    station.wait_exit(T);
    report(&mut vehicle, "the station gone", &|r| {
        r["peers"].get("ground/gs").is_none()
    });
    let mut impostor = Forger::new(Some(&domain_key)).unwrap();
    impostor
        .discovery(
            target,
            &Message::Hello {
                node_id: station_node_id,
                domain: net.domain.clone(),
                node: "gs".into(),
                namespace: "ground".into(),
                counter: 2,
                lease_ms: 60_000,
                gateway: false,
                asks_introduction: false,
            },
        )
        .unwrap();
    report(&mut vehicle, "the impostor heard", &|r| {
        r["peers"]["ground/gs"] == 1
    });
    impostor
        .safe(
            target,
            &[
                proof,
                Message::DeclBatch {
                    after: 0,
                    upto: 2,
                    reset: false,
                    entries: vec![
                        LoggedDeclaration {
                            counter: 1,
                            decl: Declaration::Service {
                                id: 1,
                                name: "probe".into(),
                            },
                        },
                        LoggedDeclaration {
                            counter: 2,
                            decl: Declaration::Offer {
                                id: 2,
                                service: 1,
                                kind: ItemKind::Function,
                                name: "ground/probe/fake".into(),
                                ty: marea::typeinfo::TypeInfo::of::<fn(u64) -> u64>(),
                                origin: None,
                            },
                        },
                    ],
                },
            ],
        )
        .unwrap();
    let r = report(&mut vehicle, "the replayed proof refused", &|r| {
        r["refusals"]["rejected"].as_u64() > Some(rejected_before)
    });
    assert_eq!(
        r["authenticated"],
        serde_json::json!([]),
        "the impostor was authenticated: {r}"
    );
}

/// With a roster, `<access>` matches a peer by the namespace its identity key proved, not the
/// one it claims: a domain-key holder claiming the station's namespace without a key listed for
/// it is denied the call the station may make, and the provider never runs it.
#[test]
fn access_rules_trust_only_an_authenticated_namespace() {
    let dir = tempfile::tempdir().unwrap();
    let key = keygen(dir.path(), "domain.key");
    let (station_id, station_pub) = identity_keygen(dir.path(), "station.id");
    let (evil_id, evil_pub) = identity_keygen(dir.path(), "evil.id");
    let roster = dir.path().join("identities.xml");
    std::fs::write(
        &roster,
        format!(
            r#"<identities>
  <identity key="{station_pub}" namespaces="ground"/>
  <identity key="{evil_pub}" namespaces="evil"/>
</identities>"#
        ),
    )
    .unwrap();
    let net = Net::new("auth_identity_access");
    let inbox = dir.path().join("inbox");
    std::fs::create_dir_all(&inbox).unwrap();
    let config = net.network_xml(
        dir.path(),
        "vas",
        "rover1",
        r#"<access><allow kind="call" item="rover1/vas/*" from="ground/*"/></access>"#,
    );
    let (key_s, roster_s) = (key.to_str().unwrap(), roster.to_str().unwrap());
    let mut vehicle = common::probe_with_config(
        "vas",
        &config,
        "vas",
        &["--key-file", key_s, "--identities", roster_s],
        &common::victim_cmd(&inbox),
    );
    vehicle.expect_key(T, "ready");
    let call = |node: &str, identity: Option<&Path>, arg: &str| {
        let mut args = vec!["--key-file", key_s, "--namespace", "ground"];
        if let Some(id) = identity {
            args.extend(["--identity-file", id.to_str().unwrap()]);
        }
        args.extend([
            "call",
            "--name",
            "rover1/vas/retask",
            "--arg",
            arg,
            "--wait-ms",
            "10000",
        ]);
        net.probe(node, &args)
    };
    // Claiming `ground` with no identity, then with a key listed for `evil` only.
    for (node, identity) in [("fmo", None), ("fmo2", Some(evil_id.as_path()))] {
        let mut impostor = call(node, identity, "666");
        let r = outcome(&mut impostor);
        assert_eq!(r["error"], "denied", "{node}: {r}");
    }
    let mut station = call("fmo3", Some(station_id.as_path()), "21");
    let r = outcome(&mut station);
    assert_eq!(r["ok"], 42, "{r}");
    let v = vehicle.expect(T, "the station's call run", |v| {
        v["report"]["called"]
            .as_array()
            .is_some_and(|c| !c.is_empty())
    });
    assert_eq!(v["report"]["called"], serde_json::json!([21]), "{v}");
}
