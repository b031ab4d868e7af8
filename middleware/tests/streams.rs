//! An event stream (`Event::stream`) between nodes over real UDP sockets follows its
//! subscribers as they come and go: it reads the offer's routes only when they change, and a
//! subscriber that arrives mid-stream gets every event sent once the publisher knows of it. It
//! holds back only the streams a slow reader reads, and it runs with every node on one
//! current-thread runtime.

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

/// Flow control is per stream. On node b, a slow reader of `slow` (a millisecond's pause every
/// 20 events) falls behind, and b tells a to hold the stream of `slow`; a's stream of `fast`
/// to b's other reader, which keeps up, goes on: its 100,000 events all arrive while the slow
/// reader has taken under half of its 60,000, and both streams arrive whole and in order.
/// (When a node's Flow held every stream to it, `fast` waited as long as `slow`.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_slow_reader_holds_back_only_the_stream_it_reads() {
    use std::sync::atomic::{AtomicU64, Ordering};
    use std::sync::Arc;
    const SLOW: u64 = 60_000;
    const FAST: u64 = 100_000;
    let domain = format!("streams-per-offer-{}", std::process::id());
    let a = Node::open(&cfg("a", &domain, port() + 1)).await.unwrap();
    let src = a.service("src").unwrap();
    let slow_ev = src.publish_event::<u64>("slow").unwrap();
    let fast_ev = src.publish_event::<u64>("fast").unwrap();
    let b = Node::open(&cfg("b", &domain, port() + 1)).await.unwrap();
    let dst = b.service("dst").unwrap();
    let slow_sub = dst.subscribe_event::<u64>("src/slow").unwrap();
    let fast_sub = dst.subscribe_event::<u64>("src/fast").unwrap();
    for ev in [&slow_ev, &fast_ev] {
        assert!(ev.wait_remote_subscribers(1, T).await, "b subscribed");
    }

    let slow_taken = Arc::new(AtomicU64::new(0));
    let taken = slow_taken.clone();
    let (under_way, slow_under_way) = tokio::sync::oneshot::channel();
    let slow_reader = tokio::spawn(async move {
        let mut got = Vec::with_capacity(SLOW as usize);
        let mut under_way = Some(under_way);
        while (got.len() as u64) < SLOW {
            got.push(slow_sub.recv_timeout(T).await.expect("a slow event").value);
            let n = taken.fetch_add(1, Ordering::Relaxed) + 1;
            if n == 100 {
                let _ = under_way.take().map(|tx| tx.send(()));
            }
            if n % 20 == 0 {
                tokio::time::sleep(Duration::from_millis(1)).await;
            }
        }
        got
    });
    let taken = slow_taken.clone();
    let fast_reader = tokio::spawn(async move {
        let mut got = Vec::with_capacity(FAST as usize);
        while (got.len() as u64) < FAST {
            got.push(fast_sub.recv_timeout(T).await.expect("a fast event").value);
        }
        (got, taken.load(Ordering::Relaxed))
    });

    let streams = async {
        let slow = async {
            let mut stream = slow_ev.stream();
            send_all(&mut stream, 0..SLOW).await;
            stream.flush().await.expect("slow: nothing lost");
        };
        let fast = async {
            // Once the slow stream is under way (its reader took 100): it outruns its reader
            // many times over, and b is behind on it (its mailbox over a quarter of 65,536
            // full) within milliseconds.
            slow_under_way
                .await
                .expect("the slow reader took its first 100");
            let mut stream = fast_ev.stream();
            send_all(&mut stream, 0..FAST).await;
            stream.flush().await.expect("fast: nothing lost");
        };
        tokio::join!(slow, fast);
    };
    tokio::time::timeout(Duration::from_secs(120), streams)
        .await
        .expect("both streams ended in time");
    let (fast_got, slow_taken_then) = fast_reader.await.unwrap();
    assert_eq!(fast_got, (0..FAST).collect::<Vec<u64>>(), "fast: in order");
    assert!(
        slow_taken_then < SLOW / 2,
        "the fast stream waited for the slow reader: it ended when {slow_taken_then} of {SLOW} slow events were taken"
    );
    let slow_got = slow_reader.await.unwrap();
    assert_eq!(slow_got, (0..SLOW).collect::<Vec<u64>>(), "slow: in order");
    for n in [a, b] {
        assert!(n.shutdown().await, "tasks stopped");
    }
}

/// Both nodes and their tasks on one current-thread runtime (what a program gets with
/// `#[tokio::main(flavor = "current_thread")]`): a stream of more events than its window
/// (16,384) reaches the subscriber whole and in order, the publisher waiting for
/// acknowledgements the same thread must read.
#[tokio::test(flavor = "current_thread")]
async fn a_stream_runs_with_every_node_on_one_current_thread_runtime() {
    const N: u64 = 50_000;
    let domain = format!("streams-one-thread-{}", std::process::id());
    let a = Node::open(&cfg("a", &domain, port() + 2)).await.unwrap();
    let ev = a
        .service("src")
        .unwrap()
        .publish_event::<u64>("ev")
        .unwrap();
    let b = Node::open(&cfg("b", &domain, port() + 2)).await.unwrap();
    let sub = b
        .service("dst")
        .unwrap()
        .subscribe_event::<u64>("src/ev")
        .unwrap();
    assert!(ev.wait_remote_subscribers(1, T).await, "b subscribed");
    let reader = tokio::spawn(async move {
        let mut got = Vec::with_capacity(N as usize);
        while (got.len() as u64) < N {
            got.push(sub.recv_timeout(T).await.expect("an event").value);
        }
        got
    });
    let streamed = async {
        let mut stream = ev.stream();
        send_all(&mut stream, 0..N).await;
        stream.flush().await.expect("nothing lost");
    };
    tokio::time::timeout(Duration::from_secs(60), streamed)
        .await
        .expect("the stream ended in time");
    let got = tokio::time::timeout(T, reader)
        .await
        .expect("the reader ended in time")
        .unwrap();
    assert_eq!(got, (0..N).collect::<Vec<u64>>(), "whole and in order");
}
