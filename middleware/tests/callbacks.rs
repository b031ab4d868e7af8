//! Callback subscriptions (`Service::subscribe_event_with`, `subscribe_variable_with`) between
//! two nodes over real UDP sockets: remote and local deliveries run the callback in order, a
//! callback may publish, a panicking callback does not end its link's receive task, and a
//! dropped subscription runs its callback no more.

mod common;

use std::sync::{Arc, Mutex};
use std::time::Duration;

use marea::{NetworkConfig, Node};
use tokio::sync::mpsc;

fn cfg(node: &str, domain: &str, port: u16) -> NetworkConfig {
    common::loopback_config(node, domain, 18, port, Duration::from_secs(30))
}

const T: Duration = Duration::from_secs(20);

async fn two_nodes(test: &str, port: u16) -> (Node, Node) {
    let domain = format!("{test}-{}", std::process::id());
    let a = Node::open(&cfg("a", &domain, port)).await.unwrap();
    let b = Node::open(&cfg("b", &domain, port)).await.unwrap();
    (a, b)
}

fn port(offset: u16) -> u16 {
    test_support::multicast_port(u64::from(std::process::id()) * 2) + offset
}

/// Node b's callback takes a's events as they come and republishes each on b's own event
/// `dst/echo`; a second callback on b (a local subscriber of that event) sets a variable
/// from inside it, which a reads, and declares a subscription at the first event (which
/// recomputes b's routes: run under the publisher's locks it would deadlock). Every event
/// arrives once, in order, through both callbacks.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn callbacks_take_remote_and_local_events_in_order_and_may_publish() {
    let (a, b) = two_nodes("callbacks", port(0)).await;
    let src = a.service("src").unwrap();
    let dst = b.service("dst").unwrap();
    let echo = Arc::new(dst.publish_event::<u64>("echo").unwrap());
    let count = Arc::new(dst.publish_variable::<u64>("count").unwrap());

    let remote_seen = Arc::new(Mutex::new(Vec::new()));
    let (seen, echo2) = (remote_seen.clone(), echo.clone());
    let _remote = dst
        .subscribe_event_with::<u64, _>("src/ev", move |s| {
            let s = s.expect("a u64 event");
            assert_eq!(s.publisher, "a");
            seen.lock().unwrap().push(s.value);
            echo2.raise_nowait(&s.value).expect("republished");
        })
        .unwrap();
    let local_seen = Arc::new(Mutex::new(Vec::new()));
    let declared = Arc::new(Mutex::new(None));
    let (seen, count2, dst2, declared2) = (
        local_seen.clone(),
        count.clone(),
        dst.clone(),
        declared.clone(),
    );
    let _local = dst
        .subscribe_event_with::<u64, _>("dst/echo", move |s| {
            let s = s.expect("a u64 event");
            assert_eq!(s.publisher, "b");
            if s.value == 0 {
                let sub = dst2.subscribe_event::<u64>("src/other").expect("declared");
                *declared2.lock().unwrap() = Some(sub);
            }
            seen.lock().unwrap().push(s.value);
            count2.set(&(s.value + 1)).expect("set from a callback");
        })
        .unwrap();
    let counts = src.subscribe_variable::<u64>("dst/count").unwrap();

    let ev = src.publish_event::<u64>("ev").unwrap();
    assert!(ev.wait_remote_subscribers(1, T).await, "b never subscribed");
    const N: u64 = 1000;
    let mut stream = ev.stream();
    for i in 0..N {
        stream.send(&i).await.unwrap();
    }
    tokio::time::timeout(T, stream.flush())
        .await
        .expect("acknowledged in time")
        .unwrap();
    // The last value set from the local callback reaches a: every echo ran.
    loop {
        let v = counts.recv_timeout(T).await.expect("count from b");
        if v.value == N {
            break;
        }
    }
    let want: Vec<u64> = (0..N).collect();
    assert_eq!(*remote_seen.lock().unwrap(), want, "remote callback");
    assert_eq!(*local_seen.lock().unwrap(), want, "local callback");
    assert!(
        declared.lock().unwrap().is_some(),
        "declared from the callback"
    );
    assert!(a.shutdown().await, "a's tasks stopped");
    // With its callback subscriptions still held: their tasks stop with the node.
    assert!(b.shutdown().await, "b's tasks stopped");
}

/// A callback that panics loses that one delivery and nothing else: the link's receive task
/// goes on, and later events (and the sentinel behind them) still arrive. Once the
/// subscription is dropped its callback runs no more, though a still raises to b until its
/// withdrawal arrives: events sent before a sentinel that b receives after the drop never reach
/// the callback.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_panicking_callback_loses_one_delivery_and_a_dropped_one_runs_no_more() {
    let (a, b) = two_nodes("callback-panic", port(1)).await;
    let src = a.service("src").unwrap();
    let dst = b.service("dst").unwrap();
    let (tx, mut rx) = mpsc::unbounded_channel();
    let sub = dst
        .subscribe_event_with::<u64, _>("src/ev", move |s| {
            let v = s.expect("a u64 event").value;
            if v == 3 {
                panic!("callback refuses 3");
            }
            let _ = tx.send(v);
        })
        .unwrap();
    let sentinels = dst.subscribe_event::<u64>("src/sentinel").unwrap();
    let ev = src.publish_event::<u64>("ev").unwrap();
    let sentinel = src.publish_event::<u64>("sentinel").unwrap();
    assert!(ev.wait_remote_subscribers(1, T).await, "b never subscribed");
    assert!(sentinel.wait_remote_subscribers(1, T).await);
    for i in 0..6u64 {
        ev.raise(&i).await.expect("acknowledged");
    }
    let mut got = Vec::new();
    while got.len() < 5 {
        let v = tokio::time::timeout(T, rx.recv()).await.expect("in time");
        got.push(v.expect("callback alive"));
    }
    assert_eq!(
        got,
        vec![0, 1, 2, 4, 5],
        "only the panicking delivery is lost"
    );

    drop(sub);
    // Raised while b may not have withdrawn yet at a: none reaches the dropped callback.
    for i in 6..20u64 {
        let _ = ev.raise_nowait(&i);
    }
    sentinel.raise(&1).await.expect("sentinel acknowledged");
    let s = sentinels.recv_timeout(T).await.expect("the sentinel");
    assert_eq!(s.value, 1);
    assert!(
        rx.try_recv().is_err(),
        "a dropped subscription's callback ran"
    );
    assert!(a.shutdown().await, "a's tasks stopped");
    assert!(b.shutdown().await, "b's tasks stopped");
}

/// A callback holds its link back: while b's callback runs on the first event, b's link reads
/// nothing more, so an event raised after it stays unacknowledged (the first one's own
/// acknowledgement may leave with b's next heartbeat or timer: it was taken from its datagram);
/// released, both raises complete with b's subscriber acknowledged.
#[tokio::test(flavor = "multi_thread", worker_threads = 3)]
async fn a_running_callback_holds_back_the_acknowledgement_of_what_follows() {
    let (a, b) = two_nodes("callback-ack", port(2)).await;
    let src = a.service("src").unwrap();
    let dst = b.service("dst").unwrap();
    let (entered_tx, entered_rx) = std::sync::mpsc::channel();
    let (release_tx, release_rx) = std::sync::mpsc::channel::<()>();
    let release_rx = Mutex::new(release_rx);
    let seen = Arc::new(Mutex::new(Vec::new()));
    let seen2 = seen.clone();
    let _sub = dst
        .subscribe_event_with::<u64, _>("src/ev", move |s| {
            let v = s.expect("a u64 event").value;
            seen2.lock().unwrap().push(v);
            if v == 7 {
                let _ = entered_tx.send(v);
                // Holds b's receive task until the test releases it (or its bound passes),
                // handing the worker's other tasks to another thread meanwhile (a task left in
                // its LIFO slot would otherwise wait for the callback too).
                tokio::task::block_in_place(|| {
                    let _ = release_rx.lock().unwrap().recv_timeout(T);
                });
            }
        })
        .unwrap();
    let ev = src.publish_event::<u64>("ev").unwrap();
    assert!(ev.wait_remote_subscribers(1, T).await, "b never subscribed");
    let first = ev.raise_nowait(&7).expect("raised");
    let entered = tokio::task::spawn_blocking(move || entered_rx.recv_timeout(T))
        .await
        .unwrap()
        .expect("the callback ran");
    assert_eq!(entered, 7);
    let second = ev.raise_nowait(&8).expect("raised");
    tokio::pin!(second);
    assert!(
        tokio::time::timeout(Duration::from_millis(300), &mut second)
            .await
            .is_err(),
        "an event after the running callback's was acknowledged"
    );
    release_tx.send(()).unwrap();
    for report in [first.await, second.await] {
        assert!(report.all_acknowledged(), "{report:?}");
        assert_eq!(report.acknowledged(), vec!["b/dst".to_owned()]);
    }
    assert_eq!(
        *seen.lock().unwrap(),
        vec![7, 8],
        "each event once, in order"
    );
    assert!(a.shutdown().await, "a's tasks stopped");
    assert!(b.shutdown().await, "b's tasks stopped");
}
