//! Publishing borrowed bytes (`Variable::set_bytes`, `Event::raise_bytes`) and receiving on a
//! plain thread without an async runtime (`recv_blocking`, `recv_blocking_timeout`,
//! `try_recv`), between two nodes over real UDP sockets.

mod common;

use std::time::Duration;

use marea::{NetworkConfig, Node, RecvError};

fn cfg(node: &str, domain: &str, port: u16) -> NetworkConfig {
    common::loopback_config(node, domain, 17, port, Duration::from_secs(30))
}

fn port() -> u16 {
    test_support::multicast_port(u64::from(std::process::id()))
}

const T: Duration = Duration::from_secs(20);

#[test]
fn borrowed_bytes_reach_a_plain_thread_receiving_without_a_runtime() {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let domain = format!("blocking-{}", std::process::id());
    let (a, b) = rt.block_on(async {
        let a = Node::open(&cfg("a", &domain, port())).await.unwrap();
        let b = Node::open(&cfg("b", &domain, port())).await.unwrap();
        (a, b)
    });
    let pub_svc = a.service("src").unwrap();
    let sub_svc = b.service("dst").unwrap();
    let events = sub_svc.subscribe_event::<Vec<u8>>("src/ev").unwrap();
    let values = sub_svc.subscribe_variable::<Vec<u8>>("src/var").unwrap();
    let ev = pub_svc.publish_event::<Vec<u8>>("ev").unwrap();
    let var = pub_svc.publish_variable::<Vec<u8>>("var").unwrap();
    // Nothing yet: try_recv does not block, the timed receive times out.
    assert!(events.try_recv().is_none());
    assert!(matches!(
        events.recv_blocking_timeout(Duration::from_millis(20)),
        Err(RecvError::Timeout(_))
    ));
    let matched = rt.block_on(async {
        ev.wait_remote_subscribers(1, T).await && var.wait_remote_subscribers(1, T).await
    });
    assert!(matched, "b never subscribed");

    // The receiver is a plain thread: no runtime on it.
    let receiver = std::thread::spawn(move || {
        assert!(tokio::runtime::Handle::try_current().is_err());
        let mut got = Vec::new();
        for _ in 0..100 {
            let s = events
                .recv_blocking_timeout(T)
                .expect("an event within the limit");
            assert_eq!(s.name, "src/ev");
            assert_eq!(s.publisher, "a");
            got.push(s.value);
        }
        let v = values
            .recv_blocking_timeout(T)
            .expect("the variable's value");
        (got, v.value, events)
    });
    // Published from borrowed slices of one buffer.
    let frame: Vec<u8> = (0..=255u8).cycle().take(2000).collect();
    let reports = rt.block_on(async {
        let mut pending = Vec::new();
        for i in 0..100usize {
            pending.push(ev.raise_bytes_nowait(&frame[i..i + 1000]).unwrap());
        }
        var.set_bytes(&frame[7..71]).unwrap();
        let mut reports = Vec::new();
        for p in pending {
            reports.push(
                tokio::time::timeout(T, p)
                    .await
                    .expect("acknowledged in time"),
            );
        }
        reports
    });
    assert!(
        reports.iter().all(|r| r.acknowledged() == ["b/dst"]),
        "{reports:?}"
    );
    let (got, value, events) = receiver.join().unwrap();
    for (i, g) in got.iter().enumerate() {
        assert_eq!(g[..], frame[i..i + 1000], "event {i}");
    }
    assert_eq!(value[..], frame[7..71]);
    // The same through the async path of a typed raise: identical bytes.
    let r = rt.block_on(async { ev.raise(&frame[..10].to_vec()).await.unwrap() });
    assert!(r.all_acknowledged());
    let s = events.recv_blocking_timeout(T).unwrap();
    assert_eq!(s.value[..], frame[..10]);
    assert!(events.try_recv().is_none());
    rt.block_on(async {
        drop((ev, var, pub_svc, sub_svc));
        let _ = tokio::time::timeout(T, a.shutdown()).await;
        let _ = tokio::time::timeout(T, b.shutdown()).await;
    });
}
