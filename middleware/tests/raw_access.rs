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
