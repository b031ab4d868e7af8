//! Payloads larger than one datagram or one shared-memory frame (a camera frame, a map tile set):
//! events, variables and calls of 64 KiB, 1 MiB and 16 MiB cross UDP, shared memory and a
//! gateway between the two whole and unchanged; above [`marea::protocol::MAX_PAYLOAD`], `raise`,
//! `set` and `call` refuse at once, naming the size and the limit. Real sockets and real
//! iceoryx2 shared memory, between nodes of this process.

mod common;

use std::time::Duration;

use marea::config::{LinkConfig, ShmConfig};
use marea::protocol::MAX_PAYLOAD;
use marea::{CallError, NetworkConfig, Node, PublishError};

const T: Duration = Duration::from_secs(60);
const SIZES: [usize; 3] = [64 << 10, 1 << 20, 16 << 20];

fn port() -> u16 {
    test_support::multicast_port(u64::from(std::process::id()) + 7)
}

fn udp(node: &str, domain: &str) -> NetworkConfig {
    common::loopback_config(node, domain, 21, port(), Duration::from_secs(30))
}

fn shm(node: &str, domain: &str) -> NetworkConfig {
    let mut c = NetworkConfig::ethernet_loopback(node);
    c.domain = domain.into();
    c.links = vec![LinkConfig::Shm(ShmConfig {
        service: format!("large-{domain}"),
        ..ShmConfig::default()
    })];
    c
}

/// `len` bytes no two sizes share a prefix of, so a part lost, repeated or reordered shows.
fn payload(len: usize) -> Vec<u8> {
    (0..len)
        .map(|i| (i as u32).wrapping_mul(2_654_435_761).rotate_right(7) as u8 ^ (len as u8))
        .collect()
}

/// Raises an event of every size in [`SIZES`] from `a` and checks `b` gets each whole; then a
/// variable and a call of 1 MiB each way.
async fn every_size_crosses(a: &Node, b: &Node) {
    let src = a.service("src").unwrap();
    let dst = b.service("dst").unwrap();
    let events = dst.subscribe_event::<Vec<u8>>("src/frame").unwrap();
    let values = dst.subscribe_variable::<Vec<u8>>("src/tile").unwrap();
    let ev = src.publish_event::<Vec<u8>>("frame").unwrap();
    let var = src.publish_variable::<Vec<u8>>("tile").unwrap();
    let _provider = src
        .provide_function::<Vec<u8>, Vec<u8>, _, _>("echo_reversed", |mut v: Vec<u8>| async move {
            v.reverse();
            Ok(v)
        })
        .unwrap();
    assert!(ev.wait_remote_subscribers(1, T).await, "no subscriber");
    assert!(var.wait_remote_subscribers(1, T).await, "no subscriber");
    for size in SIZES {
        let sent = payload(size);
        let report = tokio::time::timeout(T, ev.raise(&sent))
            .await
            .unwrap_or_else(|_| panic!("raising {size} bytes did not complete"))
            .expect("raise");
        assert!(
            report.all_acknowledged() && !report.acknowledged().is_empty(),
            "{size} bytes: {report:?}"
        );
        let got = events.recv_timeout(T).await.expect("the event");
        assert_eq!(got.value.len(), size);
        assert!(got.value == sent, "{size} bytes arrived changed");
    }
    let tile = payload(1 << 20);
    var.set(&tile).unwrap();
    let got = values.recv_timeout(T).await.expect("the variable");
    assert!(got.value == tile, "the 1 MiB variable arrived changed");

    let echo = dst
        .function::<Vec<u8>, Vec<u8>>("src/echo_reversed")
        .unwrap();
    assert!(echo.wait_provider(T).await, "no provider");
    let args = payload(1 << 20);
    let mut want = args.clone();
    want.reverse();
    let result = echo.call(&args, T).await.expect("the call");
    assert!(result == want, "the 1 MiB call came back changed");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn events_variables_and_calls_of_any_size_cross_udp() {
    let domain = format!("large-udp-{}", std::process::id());
    let a = Node::open(&udp("a", &domain)).await.unwrap();
    let b = Node::open(&udp("b", &domain)).await.unwrap();
    every_size_crosses(&a, &b).await;
    a.shutdown().await;
    b.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn events_variables_and_calls_of_any_size_cross_shared_memory() {
    let domain = format!("large-shm-{}", std::process::id());
    let a = Node::open(&shm("a", &domain)).await.unwrap();
    let b = Node::open(&shm("b", &domain)).await.unwrap();
    every_size_crosses(&a, &b).await;
    a.shutdown().await;
    b.shutdown().await;
}

/// A node on shared memory only, one on UDP only, and a gateway on both between them.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn events_variables_and_calls_of_any_size_cross_a_gateway_from_shm_onto_udp() {
    let domain = format!("large-gw-{}", std::process::id());
    let mut gw = udp("gw", &domain);
    gw.links.extend(shm("gw", &domain).links);
    gw.gateway = Some(true);
    let gw = Node::open(&gw).await.unwrap();
    let a = Node::open(&shm("a", &domain)).await.unwrap();
    let b = Node::open(&udp("b", &domain)).await.unwrap();
    every_size_crosses(&a, &b).await;
    for n in [a, b, gw] {
        n.shutdown().await;
    }
}

/// A command does not wait behind a camera's frames: a call made while 64 MiB of frames are
/// queued towards its provider is answered before the last of them arrives, and every frame
/// still arrives whole, once, in order.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_call_passes_the_frames_queued_before_it() {
    use std::sync::atomic::{AtomicUsize, Ordering};
    use std::sync::Arc;
    const FRAMES: usize = 16;
    const FRAME: usize = 4 << 20;
    let domain = format!("large-urgent-{}", std::process::id());
    let vehicle = Node::open(&udp("vehicle", &domain)).await.unwrap();
    let ground = Node::open(&udp("ground", &domain)).await.unwrap();
    let cam = vehicle.service("cam").unwrap();
    let gs = ground.service("gs").unwrap();
    let arrived = Arc::new(AtomicUsize::new(0));
    let out_of_order = Arc::new(AtomicUsize::new(0));
    let (a, o) = (arrived.clone(), out_of_order.clone());
    let _frames = gs
        .subscribe_event_with::<Vec<u8>, _>("cam/frame", move |s| {
            let Ok(s) = s else { return };
            let n = a.fetch_add(1, Ordering::SeqCst);
            let index = u64::from_le_bytes(s.value[..8].try_into().unwrap());
            if index != n as u64 || s.value.len() != FRAME {
                o.fetch_add(1, Ordering::SeqCst);
            }
        })
        .unwrap();
    let _ping = gs
        .provide_function("ping", |x: u32| async move { Ok::<u32, String>(x + 1) })
        .unwrap();
    let ev = cam.publish_event::<Vec<u8>>("frame").unwrap();
    let ping = cam.function::<u32, u32>("gs/ping").unwrap();
    assert!(ev.wait_remote_subscribers(1, T).await, "no subscriber");
    assert!(ping.wait_provider(T).await, "no provider");
    let pending: Vec<_> = (0..FRAMES as u64)
        .map(|i| {
            let mut frame = vec![0x5a; FRAME];
            frame[..8].copy_from_slice(&i.to_le_bytes());
            ev.raise_nowait(&frame).unwrap()
        })
        .collect();
    assert_eq!(ping.call(&7, T).await.expect("the call"), 8);
    let before = arrived.load(Ordering::SeqCst);
    assert!(
        before < FRAMES,
        "the call was answered only after all {FRAMES} frames queued before it"
    );
    for p in pending {
        let report = tokio::time::timeout(T, p).await.expect("frames delivered");
        assert!(report.all_acknowledged(), "{report:?}");
    }
    assert_eq!(arrived.load(Ordering::SeqCst), FRAMES, "every frame once");
    assert_eq!(out_of_order.load(Ordering::SeqCst), 0, "whole and in order");
    eprintln!("the call was answered after {before} of {FRAMES} frames");

    // Calls keep their order among themselves: a call too large for one datagram (its parts
    // wait behind the frames) is not passed by a small one made after it.
    let seen = Arc::new(std::sync::Mutex::new(Vec::new()));
    let s = seen.clone();
    let _note = gs
        .provide_function("note", move |args: Vec<u8>| {
            let s = s.clone();
            async move {
                s.lock().unwrap().push(args.len());
                Ok::<usize, String>(args.len())
            }
        })
        .unwrap();
    let note = cam.function::<Vec<u8>, usize>("gs/note").unwrap();
    assert!(note.wait_provider(T).await, "no provider");
    let pending: Vec<_> = (0..4u64)
        .map(|i| {
            let mut frame = vec![0x5a; FRAME];
            frame[..8].copy_from_slice(&(FRAMES as u64 + i).to_le_bytes());
            ev.raise_nowait(&frame).unwrap()
        })
        .collect();
    let (big_args, small_args) = (vec![1u8; 200_000], vec![2u8; 10]);
    let (big, small) = tokio::join!(note.call(&big_args, T), note.call(&small_args, T));
    assert_eq!((big.expect("big"), small.expect("small")), (200_000, 10));
    assert_eq!(
        *seen.lock().unwrap(),
        vec![200_000, 10],
        "in the order made"
    );
    for p in pending {
        tokio::time::timeout(T, p).await.expect("frames delivered");
    }
    vehicle.shutdown().await;
    ground.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_payload_over_the_limit_is_refused_at_once_naming_its_size_and_the_limit() {
    let domain = format!("large-limit-{}", std::process::id());
    let a = Node::open(&udp("a", &domain)).await.unwrap();
    let b = Node::open(&udp("b", &domain)).await.unwrap();
    let src = a.service("src").unwrap();
    let dst = b.service("dst").unwrap();
    let _events = dst.subscribe_event::<Vec<u8>>("src/frame").unwrap();
    let ev = src.publish_event::<Vec<u8>>("frame").unwrap();
    let var = src.publish_variable::<Vec<u8>>("tile").unwrap();
    let _provider = src
        .provide_function::<Vec<u8>, usize, _, _>("size", |v: Vec<u8>| async move { Ok(v.len()) })
        .unwrap();
    assert!(ev.wait_remote_subscribers(1, T).await, "no subscriber");
    let over = vec![0u8; MAX_PAYLOAD + 1];
    let too_large = |e: &PublishError| {
        matches!(e, PublishError::TooLarge { name, size, max }
            if (name == "src/frame" || name == "src/tile") && *size > MAX_PAYLOAD && *max == MAX_PAYLOAD)
    };
    // A `Vec<u8>` encodes with its length first: a few bytes more than it holds.
    let e = ev.raise_nowait(&over).err().expect("refused");
    assert!(too_large(&e), "{e}");
    let text = e.to_string();
    assert!(
        text.contains(&MAX_PAYLOAD.to_string()) && text.contains("src/frame"),
        "{text}"
    );
    let e = ev.raise_bytes_nowait(&over).err().expect("refused");
    assert!(too_large(&e), "{e}");
    assert!(
        e.to_string().contains(&(MAX_PAYLOAD + 1).to_string()),
        "{e}"
    );
    assert!(too_large(&var.set(&over).expect_err("refused")));
    assert!(too_large(&var.set_bytes(&over).expect_err("refused")));
    // Exactly at the limit, it goes (bytes: the payload is the bytes themselves).
    let at = vec![1u8; MAX_PAYLOAD];
    let report = tokio::time::timeout(T, ev.raise_bytes(&at))
        .await
        .expect("raising the largest payload did not complete")
        .expect("the largest payload is taken");
    assert!(
        report.all_acknowledged() && !report.acknowledged().is_empty(),
        "{report:?}"
    );

    let size = dst.function::<Vec<u8>, usize>("src/size").unwrap();
    assert!(size.wait_provider(T).await, "no provider");
    let started = std::time::Instant::now();
    match size.call(&over, T).await {
        Err(CallError::TooLarge { name, size, max }) => {
            assert_eq!((name.as_str(), max), ("src/size", MAX_PAYLOAD));
            assert!(size > MAX_PAYLOAD);
        }
        other => panic!("expected TooLarge, got {other:?}"),
    }
    assert!(
        started.elapsed() < T / 2,
        "refused at once, not after a timeout"
    );
    a.shutdown().await;
    b.shutdown().await;
}
