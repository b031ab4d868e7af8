//! Two nodes whose only common medium is a Zenoh router (real TCP on loopback, a real Zenoh
//! router in router mode, no multicast): they meet and every primitive holds across it as
//! across a LAN; and across a router restart, events raised while it is down arrive once each,
//! in order, after it is back.

#![cfg(feature = "zenoh")]

use std::time::Duration;

use marea::{CallError, NetworkConfig, Node, SendFileOptions};

const T: Duration = Duration::from_secs(20);

/// A free TCP port on loopback (bound and released; a router then listens on it).
fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .map(|a| a.port())
        .expect("a free loopback port")
}

/// A Zenoh router listening on `port`, with multicast scouting off.
async fn router(port: u16) -> zenoh::Session {
    let mut c = zenoh::Config::default();
    let set = |c: &mut zenoh::Config, k: &str, v: &str| c.insert_json5(k, v).expect(k);
    set(&mut c, "mode", "\"router\"");
    set(
        &mut c,
        "listen/endpoints",
        &format!("[\"tcp/127.0.0.1:{port}\"]"),
    );
    set(&mut c, "scouting/multicast/enabled", "false");
    zenoh::open(c).await.expect("router opens")
}

/// Node `node` of `domain` with a single `<zenoh>` link, a client of the router at `port`,
/// with the default heartbeat and lease (1 s, 10 s: a router restart fits in the lease).
fn config(node: &str, domain: &str, port: u16) -> NetworkConfig {
    let xml = format!(
        r#"<network node="{node}" namespace="{node}" domain="{domain}">
             <zenoh name="wan" mode="client" connect="tcp/127.0.0.1:{port}"/>
           </network>"#
    );
    NetworkConfig::parse(&xml, None).expect("a valid network file")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_nodes_meet_through_a_router_and_every_primitive_holds() {
    let port = free_port();
    let r = router(port).await;
    let domain = format!("zenoh-{}", std::process::id());
    let air = Node::open(&config("air", &domain, port)).await.unwrap();
    let vas = air.service("vas").unwrap();
    let position = vas.publish_variable::<(f64, f64)>("position").unwrap();
    position.set(&(41.3, 2.1)).unwrap();
    let alarm = vas.publish_event::<String>("alarm").unwrap();
    let _change = vas
        .provide_function("change_state", |to: String| async move {
            if to == "FLYING" {
                Err("refused: not armed".to_owned())
            } else {
                Ok(format!("now {to}"))
            }
        })
        .unwrap();
    let inbox = tempfile::tempdir().unwrap();
    let sink = vas.file_sink("plans", inbox.path()).unwrap();

    // The ground node joins later: it gets the variable's last value at once.
    let ground = Node::open(&config("ground", &domain, port)).await.unwrap();
    let fmo = ground.service("fmo").unwrap();
    let pos = fmo
        .subscribe_variable::<(f64, f64)>("air/vas/position")
        .unwrap();
    let got = pos.recv_timeout(T).await.expect("the last value");
    assert_eq!(got.value, (41.3, 2.1));
    assert!(
        air.link_addrs().iter().any(|a| a.starts_with("zenoh://")),
        "{:?}",
        air.link_addrs()
    );

    // Events: every one, once, in order, and raise says who acknowledged.
    let alarms = fmo.subscribe_event::<String>("air/vas/alarm").unwrap();
    assert!(
        alarm.wait_remote_subscribers(1, T).await,
        "ground subscribed"
    );
    let report = alarm.raise(&"first".to_owned()).await.unwrap();
    assert!(report.all_acknowledged(), "{report:?}");
    assert_eq!(report.acknowledged().len(), 1, "{report:?}");
    let mut stream = alarm.stream();
    for i in 0..2000 {
        stream.send(&format!("a{i}")).await.unwrap();
    }
    tokio::time::timeout(T, stream.flush())
        .await
        .expect("flushed in time")
        .expect("nothing lost");
    assert_eq!(alarms.recv_timeout(T).await.unwrap().value, "first");
    for i in 0..2000 {
        assert_eq!(alarms.recv_timeout(T).await.unwrap().value, format!("a{i}"));
    }

    // Calls: a result, a handler's refusal, and no provider.
    let change = fmo
        .function::<String, String>("air/vas/change_state")
        .unwrap();
    assert!(change.wait_provider(T).await);
    assert_eq!(
        change.call(&"PARKING".to_owned(), T).await.unwrap(),
        "now PARKING"
    );
    match change.call(&"FLYING".to_owned(), T).await {
        Err(CallError::Remote { .. }) => {}
        other => panic!("expected the handler's refusal, got {other:?}"),
    }
    let nobody = fmo.function::<String, String>("air/vas/nobody").unwrap();
    match nobody.call(&"x".to_owned(), Duration::from_secs(1)).await {
        Err(CallError::NoProvider { .. }) => {}
        other => panic!("expected NoProvider, got {other:?}"),
    }

    // Files: whole and verified.
    let src = tempfile::tempdir().unwrap();
    let data: Vec<u8> = (0..300_000u32).map(|i| (i * 7 % 251) as u8).collect();
    let path = src.path().join("plan.bin");
    std::fs::write(&path, &data).unwrap();
    let transfer = fmo.send_file(&path, "air/vas/plans", SendFileOptions::default());
    let received = sink.recv_timeout(T).await.expect("file received");
    assert_eq!(received.from, "ground");
    assert_eq!(std::fs::read(&received.path).unwrap(), data);
    transfer.wait().await.expect("transfer reported");

    ground.shutdown().await;
    air.shutdown().await;
    r.close().await.unwrap();
}

/// The router stops while events are raised and comes back on the same port: the clients
/// reconnect and every event arrives once, in order.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn events_raised_while_the_router_restarts_arrive_once_in_order() {
    let port = free_port();
    let r = router(port).await;
    let domain = format!("zenoh-restart-{}", std::process::id());
    let air = Node::open(&config("air", &domain, port)).await.unwrap();
    let ev = air
        .service("vas")
        .unwrap()
        .publish_event::<u32>("alarm")
        .unwrap();
    let ground = Node::open(&config("ground", &domain, port)).await.unwrap();
    let sub = ground
        .service("fmo")
        .unwrap()
        .subscribe_event::<u32>("air/vas/alarm")
        .unwrap();
    assert!(ev.wait_remote_subscribers(1, T).await, "ground subscribed");
    for i in 0..100 {
        ev.raise_nowait(&i).unwrap();
    }
    r.close().await.unwrap();
    // Raised with no router: the datagrams go nowhere, and the ARQ keeps them.
    let pending: Vec<_> = (100..200).map(|i| ev.raise_nowait(&i).unwrap()).collect();
    tokio::time::sleep(Duration::from_secs(1)).await; // the outage itself, not a synchronisation
    let r = router(port).await;
    let back = std::time::Instant::now();
    for p in pending {
        let report = tokio::time::timeout(T, p)
            .await
            .expect("acknowledged after the restart");
        assert!(report.all_acknowledged(), "{report:?}");
    }
    eprintln!(
        "acknowledged {:?} after the router came back",
        back.elapsed()
    );
    for i in 0..200 {
        let got = sub.recv_timeout(T).await.expect("every event");
        assert_eq!(got.value, i, "once each, in order");
    }
    assert!(
        sub.recv_timeout(Duration::from_millis(300)).await.is_err(),
        "nothing twice"
    );
    ground.shutdown().await;
    air.shutdown().await;
    r.close().await.unwrap();
}

/// The deployment of a vehicle beyond one LAN: its services on their LAN, one gateway node with
/// a LAN link and a `<zenoh>` link, and the ground station reaching the router only. The ground
/// reads a variable, gets every event and calls a function of a node it has no link with.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_gateway_joins_a_lan_to_nodes_beyond_a_router() {
    let port = free_port();
    let r = router(port).await;
    let domain = format!("zenoh-gw-{}", std::process::id());
    let mcast = 41_000 + (std::process::id() % 20_000) as u16;
    let lan = format!(
        r#"<ethernet bind="127.0.0.1:0" multicast="239.255.77.23:{mcast}" interface="127.0.0.1" heartbeatMs="200"/>"#
    );
    let wan = format!(r#"<zenoh mode="client" connect="tcp/127.0.0.1:{port}"/>"#);
    let xml = |node: &str, gateway: bool, links: &str| {
        let text = format!(
            r#"<network node="{node}" namespace="{node}" domain="{domain}" gateway="{gateway}">{links}</network>"#
        );
        NetworkConfig::parse(&text, None).expect("a valid network file")
    };
    let vas = Node::open(&xml("rover1", false, &lan)).await.unwrap();
    let gw = Node::open(&xml("gw", true, &format!("{lan}{wan}")))
        .await
        .unwrap();
    assert!(gw.is_gateway());
    let svc = vas.service("vas").unwrap();
    let position = svc.publish_variable::<u32>("position").unwrap();
    position.set(&7).unwrap();
    let alarm = svc.publish_event::<u32>("alarm").unwrap();
    let _f = svc
        .provide_function("double", |x: u64| async move { Ok::<u64, String>(x * 2) })
        .unwrap();

    let ground = Node::open(&xml("ground", false, &wan)).await.unwrap();
    let fmo = ground.service("fmo").unwrap();
    let pos = fmo
        .subscribe_variable::<u32>("rover1/vas/position")
        .unwrap();
    assert_eq!(
        pos.recv_timeout(T)
            .await
            .expect("through the gateway")
            .value,
        7
    );
    let alarms = fmo.subscribe_event::<u32>("rover1/vas/alarm").unwrap();
    assert!(
        alarm.wait_remote_subscribers(1, T).await,
        "ground's interest crossed"
    );
    for i in 0..500 {
        alarm.raise_nowait(&i).unwrap();
    }
    for i in 0..500 {
        assert_eq!(alarms.recv_timeout(T).await.unwrap().value, i);
    }
    let double = fmo.function::<u64, u64>("rover1/vas/double").unwrap();
    assert!(double.wait_provider(T).await);
    assert_eq!(double.call(&21, T).await.unwrap(), 42);

    ground.shutdown().await;
    gw.shutdown().await;
    vas.shutdown().await;
    r.close().await.unwrap();
}

/// The domain seal and `<access>` rules hold across a router as on a LAN: with the domain key,
/// nodes meet and the call a rule allows runs; a node without the key, on the same router and
/// domain, meets no one; a node the rule does not name is `Denied`.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_seal_and_access_rules_hold_across_a_router() {
    let port = free_port();
    let r = router(port).await;
    let dir = tempfile::tempdir().unwrap();
    let key = dir.path().join("domain.key");
    marea::link::auth::DomainKey::create_file(&key).unwrap();
    let domain = format!("zenoh-sealed-{}", std::process::id());
    let xml = |node: &str, inner: &str| {
        let text = format!(
            r#"<network node="{node}" namespace="{node}" domain="{domain}">
                 <zenoh mode="client" connect="tcp/127.0.0.1:{port}"/>
                 {inner}
               </network>"#
        );
        NetworkConfig::parse(&text, None).expect("a valid network file")
    };
    let sealed = format!(r#"<security keyFile="{}"/>"#, key.display());
    let air = Node::open(&xml(
        "air",
        &format!(
            r#"{sealed}<access trustClaims="yes"><allow kind="call" item="air/vas/change_state" from="ground/*"/></access>"#
        ),
    ))
    .await
    .unwrap();
    let _f = air
        .service("vas")
        .unwrap()
        .provide_function("change_state", |x: u8| async move { Ok::<u8, String>(x) })
        .unwrap();
    let ground = Node::open(&xml("ground", &sealed)).await.unwrap();
    let other = Node::open(&xml("other", &sealed)).await.unwrap();
    let outsider = Node::open(&xml("outsider", "")).await.unwrap();

    let call = |node: &Node| {
        node.service("caller")
            .unwrap()
            .function::<u8, u8>("air/vas/change_state")
            .unwrap()
    };
    let from_ground = call(&ground);
    assert!(from_ground.wait_provider(T).await, "sealed nodes meet");
    assert_eq!(from_ground.call(&7, T).await.unwrap(), 7);
    let from_other = call(&other);
    assert!(from_other.wait_provider(T).await);
    match from_other.call(&7, T).await {
        Err(CallError::Denied { .. }) => {}
        x => panic!("expected Denied for a node the rule does not name, got {x:?}"),
    }
    // Whoever sees the air node would have seen it by now: the ground did, seconds ago.
    let from_outsider = call(&outsider);
    assert!(
        !from_outsider.wait_provider(Duration::from_secs(3)).await,
        "a node without the key met the sealed domain"
    );
    assert!(outsider.peers().is_empty(), "{:?}", outsider.peers());
    assert!(
        air.link_stats().iter().any(|(_, s)| s.auth_rejected > 0),
        "the outsider's datagrams reached the air node and were refused"
    );

    outsider.shutdown().await;
    other.shutdown().await;
    ground.shutdown().await;
    air.shutdown().await;
    r.close().await.unwrap();
}
