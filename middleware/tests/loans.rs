//! Large events and variables written in place (`Event::<Blob>::loan`, `Variable::<Blob>::loan`): towards one subscriber on the same
//! host the buffer is a sample of its shared-memory inbox and the subscriber's `Blob` a view of
//! it (no copy either side), sealed or not; a subscriber holding many blobs gets copies past
//! the lending bound and the publisher never stalls; several subscribers, or another link, get
//! the event as any other. Real iceoryx2 shared memory and real sockets, between nodes of this
//! process.

mod common;

use std::io::Write;
use std::time::Duration;

use marea::config::{LinkConfig, SecurityConfig, ShmConfig};
use marea::link::shm::{LENT_SAMPLES, LOAN_MAX};
use marea::{Blob, Event, EventSubscriber, NetworkConfig, Node, Variable, VariableSubscriber};

const T: Duration = Duration::from_secs(60);

fn shm(node: &str, domain: &str) -> NetworkConfig {
    let mut c = NetworkConfig::ethernet_loopback(node);
    c.domain = domain.into();
    c.links = vec![LinkConfig::Shm(ShmConfig {
        service: format!("loans-{domain}"),
        ..ShmConfig::default()
    })];
    c
}

/// `len` bytes no two sizes share a prefix of, so a part lost or moved shows.
fn payload(len: usize, salt: u8) -> Vec<u8> {
    (0..len)
        .map(|i| (i as u32).wrapping_mul(2_654_435_761).rotate_right(7) as u8 ^ salt)
        .collect()
}

/// Raises `bytes` through a loan (written in two appends), checks the report and returns
/// whether the loan was shared memory.
async fn raise_loaned(ev: &Event<Blob>, bytes: &[u8]) -> bool {
    let mut loan = ev.loan(bytes.len()).expect("a loan");
    assert_eq!(loan.len(), bytes.len());
    let half = bytes.len() / 2;
    assert_eq!(loan.append(&bytes[..half]), half);
    loan.write_all(&bytes[half..]).expect("the rest fits");
    assert_eq!(loan.written(), bytes.len());
    assert_eq!(loan.append(b"x"), 0, "nothing past the end");
    let shared = loan.is_shared_memory();
    let report = tokio::time::timeout(T, loan.raise())
        .await
        .expect("the raise completes");
    assert!(
        report.all_acknowledged() && !report.acknowledged().is_empty(),
        "{report:?}"
    );
    shared
}

async fn next(sub: &EventSubscriber<Blob>) -> Blob {
    sub.recv_timeout(T).await.expect("the event").value
}

/// Nodes `a` and `b` on one shared-memory link, with `security`; a subscriber of `src/frame`
/// on `b` and its publisher on `a`, matched.
async fn event_pair<P: marea::Payload>(
    domain: &str,
    security: Option<SecurityConfig>,
) -> (Node, Node, Event<P>, EventSubscriber<P>) {
    let mut ca = shm("a", domain);
    let mut cb = shm("b", domain);
    ca.security = security.clone();
    cb.security = security;
    let a = Node::open(&ca).await.unwrap();
    let b = Node::open(&cb).await.unwrap();
    let sub = b
        .service("dst")
        .unwrap()
        .subscribe_event::<P>("src/frame")
        .unwrap();
    let ev = a
        .service("src")
        .unwrap()
        .publish_event::<P>("frame")
        .unwrap();
    assert!(ev.wait_remote_subscribers(1, T).await, "no subscriber");
    (a, b, ev, sub)
}

/// [`event_pair`] of `Event<Blob>`.
async fn pair(
    domain: &str,
    security: Option<SecurityConfig>,
) -> (Node, Node, Event<Blob>, EventSubscriber<Blob>) {
    event_pair(domain, security).await
}

/// Raises events until a loan is shared memory (the first asks for the subscriber's bulk
/// inbox to be opened and goes as a copy, through that inbox once it is open: the next is
/// lent); each arrives whole.
async fn until_lent(ev: &Event<Blob>, sub: &EventSubscriber<Blob>) {
    for i in 0..200u8 {
        let sent = payload(100_000, i);
        let shared = raise_loaned(ev, &sent).await;
        let got = next(sub).await;
        assert!(*got == sent[..], "a warm-up event arrived changed");
        if shared {
            assert!(got.is_shared_memory(), "lent, but it arrived as a copy");
            return;
        }
    }
    panic!("no loan was ever shared memory");
}

async fn frames_arrive_in_place(domain: &str, security: Option<SecurityConfig>) {
    let (a, b, ev, sub) = pair(domain, security).await;
    until_lent(&ev, &sub).await;
    for (k, size) in [64 << 10, 4 << 20, LOAN_MAX - 64].into_iter().enumerate() {
        let sent = payload(size, k as u8);
        assert!(raise_loaned(&ev, &sent).await, "{size} bytes: not lent");
        let got = next(&sub).await;
        assert_eq!(got.len(), size);
        assert!(*got == sent[..], "{size} bytes arrived changed");
        assert!(got.is_shared_memory(), "{size} bytes arrived as a copy");
    }
    // Past the bound a loan is an ordinary buffer, and the frame goes in pieces.
    let sent = payload(LOAN_MAX + 1, 9);
    assert!(!raise_loaned(&ev, &sent).await, "lent past LOAN_MAX");
    assert!(*next(&sub).await == sent[..]);
    // Written anywhere through the slice: what was not written arrives as zeros.
    let mut loan = ev.loan(1 << 20).unwrap();
    assert!(loan.is_shared_memory());
    loan.append(&[7; 10]);
    let s = loan.as_mut_slice();
    s[1000] = 9;
    let report = loan.raise().await;
    assert!(report.all_acknowledged(), "{report:?}");
    let got = next(&sub).await;
    assert_eq!(&got[..10], &[7; 10]);
    assert_eq!(got[1000], 9);
    assert!(got[10..1000].iter().chain(&got[1001..]).all(|b| *b == 0));
    a.shutdown().await;
    b.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_loaned_frame_crosses_shared_memory_in_place() {
    frames_arrive_in_place(&format!("loans-{}", std::process::id()), None).await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_loaned_frame_crosses_a_sealed_shared_memory_link_in_place() {
    let dir = tempfile::tempdir().unwrap();
    let key = dir.path().join("domain.key");
    marea::link::auth::DomainKey::create_file(&key).unwrap();
    let xml = format!(
        r#"<network node="x" domain="d"><shm/><security keyFile="{}"/></network>"#,
        key.display()
    );
    let security = NetworkConfig::parse(&xml, None)
        .expect("a valid network file")
        .security;
    assert!(security.is_some());
    frames_arrive_in_place(&format!("loans-sealed-{}", std::process::id()), security).await;
}

/// A subscriber keeping every frame: past the lending bound its frames are copies (and the
/// publisher goes on); once it lets them go, frames are views again.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_subscriber_holding_frames_gets_copies_past_the_bound_and_never_stalls_the_publisher() {
    let (a, b, ev, sub) = pair(&format!("loans-held-{}", std::process::id()), None).await;
    until_lent(&ev, &sub).await;
    let mut kept = Vec::new();
    for i in 0..12u8 {
        let sent = payload(1 << 20, i);
        raise_loaned(&ev, &sent).await;
        let got = next(&sub).await;
        assert!(*got == sent[..], "frame {i} arrived changed");
        kept.push(got);
    }
    let shared = kept.iter().filter(|b| b.is_shared_memory()).count();
    assert!(
        (1..=LENT_SAMPLES).contains(&shared),
        "{shared} of 12 held frames are views: some, at most {LENT_SAMPLES}"
    );
    kept.clear();
    let sent = payload(1 << 20, 99);
    raise_loaned(&ev, &sent).await;
    let got = next(&sub).await;
    assert!(*got == sent[..]);
    assert!(got.is_shared_memory(), "released, frames are views again");
    a.shutdown().await;
    b.shutdown().await;
}

/// Loans kept without being raised never take the last sample a copied large message needs
/// from the subscriber's bulk inbox: it goes meanwhile, and the loans after it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn loans_kept_unraised_never_stall_a_copied_frame() {
    let (a, b, ev, sub) = pair(&format!("loans-kept-{}", std::process::id()), None).await;
    until_lent(&ev, &sub).await;
    let kept: Vec<_> = (0..4).map(|_| ev.loan(1 << 20).expect("a loan")).collect();
    let lent = kept.iter().filter(|l| l.is_shared_memory()).count();
    assert!(
        (1..4).contains(&lent),
        "{lent} of 4 kept loans are shared memory"
    );
    let sent = payload(1 << 20, 42);
    let report = tokio::time::timeout(T, ev.raise(&Blob::from(sent.clone())))
        .await
        .expect("a copied frame is not stalled by kept loans")
        .expect("raise");
    assert!(report.all_acknowledged(), "{report:?}");
    assert!(*next(&sub).await == sent[..]);
    for (i, mut loan) in kept.into_iter().enumerate() {
        let frame = payload(1 << 20, i as u8);
        loan.append(&frame);
        let report = tokio::time::timeout(T, loan.raise()).await.expect("raised");
        assert!(report.all_acknowledged(), "{report:?}");
        assert!(
            *next(&sub).await == frame[..],
            "kept loan {i} arrived changed"
        );
    }
    a.shutdown().await;
    b.shutdown().await;
}

/// With two subscriber nodes the loan is an ordinary buffer, and both get the frame.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_frame_for_two_subscribers_is_loaned_on_the_heap_and_reaches_both() {
    let domain = format!("loans-two-{}", std::process::id());
    let (a, b, ev, sub) = pair(&domain, None).await;
    let c = Node::open(&shm("c", &domain)).await.unwrap();
    let sub_c = c
        .service("dst")
        .unwrap()
        .subscribe_event::<Blob>("src/frame")
        .unwrap();
    assert!(
        ev.wait_remote_subscribers(2, T).await,
        "no second subscriber"
    );
    let sent = payload(3 << 20, 5);
    assert!(!raise_loaned(&ev, &sent).await, "lent with two subscribers");
    for s in [&sub, &sub_c] {
        let got = next(s).await;
        assert!(*got == sent[..], "a subscriber got it changed");
    }
    for n in [a, b, c] {
        n.shutdown().await;
    }
}

/// Over UDP nothing is lent: the frame goes as any event and arrives whole.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_loaned_frame_over_udp_is_an_ordinary_event() {
    let domain = format!("loans-udp-{}", std::process::id());
    let port = test_support::multicast_port(u64::from(std::process::id()) + 11);
    let cfg = |n: &str| common::loopback_config(n, &domain, 23, port, Duration::from_secs(30));
    let a = Node::open(&cfg("a")).await.unwrap();
    let b = Node::open(&cfg("b")).await.unwrap();
    let sub = b
        .service("dst")
        .unwrap()
        .subscribe_event::<Blob>("src/frame")
        .unwrap();
    let ev = a
        .service("src")
        .unwrap()
        .publish_event::<Blob>("frame")
        .unwrap();
    assert!(ev.wait_remote_subscribers(1, T).await, "no subscriber");
    let sent = payload(2 << 20, 3);
    assert!(!raise_loaned(&ev, &sent).await, "a UDP link lent a buffer");
    let got = next(&sub).await;
    assert!(*got == sent[..]);
    assert!(!got.is_shared_memory());
    a.shutdown().await;
    b.shutdown().await;
}

async fn next_value(sub: &VariableSubscriber<Blob>) -> Blob {
    sub.recv_timeout(T).await.expect("a value").value
}

/// Sets `bytes` through a loan; returns whether it was shared memory.
fn set_loaned(var: &Variable<Blob>, bytes: &[u8]) -> bool {
    let mut loan = var.loan(bytes.len()).expect("a loan");
    assert_eq!(loan.append(bytes), bytes.len());
    let shared = loan.is_shared_memory();
    loan.set();
    shared
}

/// A variable's value written in place reaches its one subscriber as a view of shared memory;
/// a late joiner still gets the newest value (the publisher keeps a copy).
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_loaned_variable_value_crosses_shared_memory_in_place_and_late_joiners_get_it() {
    let domain = format!("loans-var-{}", std::process::id());
    let a = Node::open(&shm("a", &domain)).await.unwrap();
    let b = Node::open(&shm("b", &domain)).await.unwrap();
    let sub = b
        .service("dst")
        .unwrap()
        .subscribe_variable::<Blob>("src/tile")
        .unwrap();
    let var = a
        .service("src")
        .unwrap()
        .publish_variable::<Blob>("tile")
        .unwrap();
    assert!(var.wait_remote_subscribers(1, T).await, "no subscriber");
    let mut lent = false;
    for i in 0..200u8 {
        let sent = payload(200_000, i);
        lent = set_loaned(&var, &sent);
        let got = next_value(&sub).await;
        assert!(*got == sent[..], "a value arrived changed");
        if lent {
            assert!(got.is_shared_memory(), "lent, but it arrived as a copy");
            break;
        }
    }
    assert!(lent, "no loan was ever shared memory");
    let tile = payload(4 << 20, 77);
    assert!(set_loaned(&var, &tile), "the 4 MiB value was not lent");
    let got = next_value(&sub).await;
    assert!(*got == tile[..], "the 4 MiB value arrived changed");
    assert!(got.is_shared_memory());

    let c = Node::open(&shm("c", &domain)).await.unwrap();
    let late = c
        .service("late")
        .unwrap()
        .subscribe_variable::<Blob>("src/tile")
        .unwrap();
    let got = next_value(&late).await;
    assert!(*got == tile[..], "the late joiner got another value");
    for n in [a, b, c] {
        n.shutdown().await;
    }
}

/// A camera frame with a header: its `Blob` field arrives as a view of the shared memory the
/// message came in (a message of one bulk sample, up to 256 KiB), without a loan.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_blob_field_of_a_struct_arrives_as_a_view_of_shared_memory() {
    #[derive(serde::Serialize, serde::Deserialize)]
    struct Frame {
        seq: u64,
        pixels: Blob,
    }
    let domain = format!("loans-field-{}", std::process::id());
    let (a, b, ev, sub) = event_pair::<Frame>(&domain, None).await;
    for seq in 0..3u64 {
        let pixels = payload(200_000, seq as u8);
        let frame = Frame {
            seq,
            pixels: Blob::from(pixels.clone()),
        };
        let report = ev.raise(&frame).await.expect("raise");
        assert!(report.all_acknowledged(), "{report:?}");
        let got = sub.recv_timeout(T).await.expect("the frame").value;
        assert_eq!(got.seq, seq);
        assert!(*got.pixels == pixels[..], "frame {seq} arrived changed");
        assert!(got.pixels.is_shared_memory(), "frame {seq}: a copy");
    }
    a.shutdown().await;
    b.shutdown().await;
}
