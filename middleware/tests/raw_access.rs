//! Type-agnostic access, as tools use it: a raw subscription receives any type with the
//! publisher's type name, and a raw call reaches a typed provider.

use std::net::{Ipv4Addr, SocketAddrV4};
use std::time::Duration;

use marea::config::{EthernetConfig, LinkConfig};
use marea::protocol::ItemKind;
use marea::{NetworkConfig, Node};

fn cfg(node: &str, domain: &str, port: u16) -> NetworkConfig {
    let mut c = NetworkConfig::ethernet_loopback(node);
    c.domain = domain.into();
    c.links = vec![LinkConfig::Ethernet(EthernetConfig {
        interface: Ipv4Addr::LOCALHOST,
        bind: "127.0.0.1:0".parse().unwrap(),
        multicast: SocketAddrV4::new(Ipv4Addr::new(239, 255, 77, 4), port),
        ..EthernetConfig::default()
    })];
    c
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn raw_subscription_and_raw_call_reach_typed_items() {
    let domain = format!("raw-{}", std::process::id());
    let port = 23_000 + (std::process::id() % 20_000) as u16;
    let vehicle = Node::open(&cfg("vehicle", &domain, port)).await.unwrap();
    let tool = Node::open(&cfg("tool", &domain, port)).await.unwrap();
    let vas = vehicle.service("vas").unwrap();
    let speed = vas.publish_variable::<(f32, u8)>("speed").unwrap();
    speed.set(&(1.5, 7)).unwrap();
    let _double = vas
        .provide_function("double", |x: u64| async move { Ok::<u64, String>(2 * x) })
        .unwrap();

    let t = tool.service("usal").unwrap();
    let raw = t.subscribe_raw(ItemKind::Variable, "vas/*").unwrap();
    let v = raw.recv_timeout(Duration::from_secs(10)).await.unwrap();
    assert_eq!(v.name, "vas/speed");
    assert_eq!(v.type_name, "(f32, u8)");
    assert_eq!(
        v.fingerprint,
        marea::typeinfo::TypeInfo::of::<(f32, u8)>().fingerprint
    );
    let decoded: (f32, u8) = marea::codec::decode_payload(&v.payload).unwrap();
    assert_eq!(decoded, (1.5, 7));

    assert!(
        tool.wait_until(Duration::from_secs(10), |n| n
            .is_offered(ItemKind::Function, "vas/double"))
            .await
    );
    let ty = t.function_type("vas/double").unwrap();
    assert_eq!(ty.name, "fn(u64) -> u64");
    let out = t
        .call_raw(
            "vas/double",
            marea::codec::encode_payload(&21u64).unwrap(),
            Duration::from_secs(2),
        )
        .await
        .unwrap();
    assert_eq!(marea::codec::decode_payload::<u64>(&out).unwrap(), 42);
    assert!(matches!(
        t.call_raw("vas/none", vec![], Duration::from_secs(1)).await,
        Err(marea::CallError::NoProvider { .. })
    ));
    drop((raw, t, speed, _double, vas));
    vehicle.shutdown().await;
    tool.shutdown().await;
}

/// `call_raw_for`: a node calling for a party that is no marea node (the Zenoh bridge's
/// clients) is heard only when it is a gateway, and the provider's `<access>` rules judge the
/// party it names, not the node.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_call_made_for_another_caller_is_judged_as_that_caller_and_only_from_a_gateway() {
    let domain = format!("raw-for-{}", std::process::id());
    let port = 23_000 + ((std::process::id() + 7_919) % 20_000) as u16;
    let mut provider_cfg = cfg("vehicle", &domain, port);
    provider_cfg.namespace = Some("vehicle".into());
    provider_cfg.access = NetworkConfig::parse(
        r#"<network node="x"><ethernet/><access trustClaims="yes">
             <allow kind="call" item="vehicle/vas/double" from="zenoh/pilot"/>
           </access></network>"#,
        None,
    )
    .unwrap()
    .access;
    let vehicle = Node::open(&provider_cfg).await.unwrap();
    let _double = vehicle
        .service("vas")
        .unwrap()
        .provide_function("double", |x: u64| async move { Ok::<u64, String>(2 * x) })
        .unwrap();
    let mut bridge_cfg = cfg("bridge", &domain, port);
    bridge_cfg.gateway = Some(true);
    let bridge = Node::open(&bridge_cfg).await.unwrap();
    let plain = Node::open(&cfg("plain", &domain, port)).await.unwrap();
    for n in [&bridge, &plain] {
        assert!(
            n.wait_until(Duration::from_secs(10), |n| n
                .is_offered(ItemKind::Function, "vehicle/vas/double"))
                .await
        );
    }
    let call = |node: &Node, who: &'static str| {
        let svc = node.service("caller").unwrap();
        async move {
            svc.call_raw_for(
                "zenoh",
                who,
                "vehicle/vas/double",
                marea::codec::encode_payload(&21u64).unwrap(),
                Duration::from_secs(5),
            )
            .await
        }
    };
    let out = call(&bridge, "pilot").await.unwrap();
    assert_eq!(marea::codec::decode_payload::<u64>(&out).unwrap(), 42);
    let guest = call(&bridge, "guest").await;
    assert!(
        matches!(guest, Err(marea::CallError::Denied { .. })),
        "{guest:?}"
    );
    // Not a gateway: whoever it names, it may not speak for anyone.
    let forged = call(&plain, "pilot").await;
    assert!(
        matches!(forged, Err(marea::CallError::Denied { .. })),
        "{forged:?}"
    );
    for n in [vehicle, bridge, plain] {
        n.shutdown().await;
    }
}
