//! An event stream (`Event::stream`) between nodes over real UDP sockets follows its
//! subscribers as they come and go: it reads the offer's routes only when they change, and a
//! subscriber that arrives mid-stream gets every event sent once the publisher knows of it.

mod common;

use std::time::Duration;

use marea::{Event, EventStream, EventSubscriber, NetworkConfig, Node};

fn cfg(node: &str, domain: &str, port: u16) -> NetworkConfig {
    common::loopback_config(node, domain, 19, port, Duration::from_secs(30))
}

const T: Duration = Duration::from_secs(20);

fn port() -> u16 {
    40_000 + (std::process::id() % 20_000) as u16
}

/// Node `name`, subscribed to a's event, once a knows of `n` subscribers.
async fn subscriber(
    domain: &str,
    name: &str,
    ev: &Event<u64>,
    n: usize,
) -> (Node, EventSubscriber<u64>) {
    let node = Node::open(&cfg(name, domain, port())).await.unwrap();
    let sub = node
        .service("dst")
        .unwrap()
        .subscribe_event::<u64>("src/ev")
        .unwrap();
    assert!(
        ev.wait_remote_subscribers(n, T).await,
        "{name} never subscribed"
    );
    (node, sub)
}

async fn send_all(stream: &mut EventStream<'_, u64>, values: std::ops::Range<u64>) {
    for i in values {
        stream.send(&i).await.unwrap();
    }
}

/// The stream starts with nobody subscribed (its events go nowhere, without error); b then
/// subscribes, and the events a streams after learning of it reach b, all of them, in order;
/// a third node c subscribes later and gets the events from then on as b does.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stream_follows_subscribers_that_arrive_mid_stream() {
    let domain = format!("streams-{}", std::process::id());
    let a = Node::open(&cfg("a", &domain, port())).await.unwrap();
    let src = a.service("src").unwrap();
    let ev = src.publish_event::<u64>("ev").unwrap();
    let mut stream = ev.stream();
    for i in 0..10 {
        stream.send(&i).await.expect("no subscriber is no error");
    }

    let (b, at_b) = subscriber(&domain, "b", &ev, 1).await;
    send_all(&mut stream, 100..1100).await;
    let (c, at_c) = subscriber(&domain, "c", &ev, 2).await;
    send_all(&mut stream, 2000..3000).await;
    tokio::time::timeout(T, stream.flush())
        .await
        .expect("acknowledged in time")
        .expect("nothing lost");

    let mut got_b = Vec::new();
    while got_b.len() < 2000 {
        got_b.push(at_b.recv_timeout(T).await.expect("an event at b").value);
    }
    let want_b: Vec<u64> = (100..1100).chain(2000..3000).collect();
    assert_eq!(
        got_b, want_b,
        "b: every event sent once a knew of it, in order"
    );
    let mut got_c = Vec::new();
    while got_c.len() < 1000 {
        got_c.push(at_c.recv_timeout(T).await.expect("an event at c").value);
    }
    assert_eq!(
        got_c,
        (2000..3000).collect::<Vec<u64>>(),
        "c: from its arrival on"
    );
    assert!(
        at_b.recv_timeout(Duration::from_millis(300)).await.is_err(),
        "b got nothing more"
    );
    for n in [a, b, c] {
        assert!(n.shutdown().await, "tasks stopped");
    }
}
