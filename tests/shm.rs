//! The shared-memory link across real processes: every node is a `marea-probe` child started
//! with its own network.xml (`--config`), shm only unless a test says otherwise. Each test uses
//! its own iceoryx2 service prefix and discovery domain, so tests run in parallel.

mod common;

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use common::{
    expect_received_in_order, ready_event_subscribers, stream_to_a_slow_reader_loses_nothing, Proc,
    T,
};
use serde_json::Value;

/// A test's shm prefix, discovery domain, multicast port and config directory.
struct ShmNet {
    service: String,
    domain: String,
    port: u16,
    dir: tempfile::TempDir,
}

impl ShmNet {
    fn new(test: &str) -> ShmNet {
        let pid = std::process::id();
        let h = test.bytes().fold(u64::from(pid), |h, b| {
            (h ^ u64::from(b)).wrapping_mul(0x100_0000_01b3)
        });
        ShmNet {
            service: format!("t{}-{pid}", test.replace('_', "-")),
            domain: format!("{test}-{pid}"),
            port: test_support::multicast_port(h),
            dir: tempfile::tempdir().expect("temp dir"),
        }
    }

    fn shm_xml(&self) -> String {
        format!(
            r#"<shm service="{}" heartbeatMs="200" leaseMs="1200"/>"#,
            self.service
        )
    }

    fn ethernet_xml(&self) -> String {
        format!(
            r#"<ethernet bind="127.0.0.1:0" interface="127.0.0.1" multicast="239.255.77.1:{}" heartbeatMs="200" leaseMs="1200"/>"#,
            self.port
        )
    }

    /// Starts a probe whose network.xml holds `links`.
    fn probe_with(&self, node: &str, links: &str, cmd: &[&str]) -> Proc {
        let path = self.dir.path().join(format!("{node}.xml"));
        let xml = format!(
            "<network node=\"{node}\" domain=\"{}\">\n  {links}\n</network>\n",
            self.domain
        );
        std::fs::write(&path, xml).expect("write network.xml");
        let mut args = vec!["--config".to_owned(), path.to_string_lossy().into_owned()];
        args.extend(cmd.iter().map(|s| s.to_string()));
        Proc::spawn(node, env!("CARGO_BIN_EXE_marea-probe"), &args)
    }

    /// A probe on shared memory only.
    fn probe(&self, node: &str, cmd: &[&str]) -> Proc {
        self.probe_with(node, &self.shm_xml(), cmd)
    }

    fn path(&self, name: &str) -> PathBuf {
        self.dir.path().join(name)
    }
}

fn pattern_file(path: &Path, len: usize) -> Vec<u8> {
    let data: Vec<u8> = (0..len as u32)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
        .collect();
    std::fs::write(path, &data).expect("write payload");
    data
}

#[test]
fn all_four_primitives_over_shared_memory_only() {
    let net = ShmNet::new("shm_four");
    // Variable: a late joiner gets the last value.
    let mut vp = net.probe("vpub", &["var-pub", "--item", "position", "--count", "5"]);
    vp.expect_key(T, "published");
    let mut vs = net.probe(
        "vsub",
        &["var-sub", "--pattern", "probe/position", "--count", "1"],
    );
    let v = vs.expect_key(T, "seq");
    assert_eq!(v["seq"], 4, "{v}");
    assert_eq!(v["publisher"], "vpub");
    // Events.
    let mut es = net.probe(
        "esub",
        &["ev-sub", "--pattern", "probe/ev", "--count", "500"],
    );
    es.expect_key(T, "ready");
    let mut ep = net.probe(
        "epub",
        &["ev-pub", "--item", "ev", "--count", "500", "--subs", "1"],
    );
    let done = ep.expect_key(T, "raised");
    assert_eq!(done["acknowledged_by_all"], 500, "{done}");
    let r = es.expect_key(T, "received");
    assert_eq!(r["received"], 500);
    assert_eq!(r["in_order"], true);
    // Function.
    let mut prov = net.probe("prov", &["provide", "--item", "double"]);
    prov.expect_key(T, "ready");
    let mut call = net.probe(
        "caller",
        &[
            "call",
            "--name",
            "probe/double",
            "--arg",
            "21",
            "--wait-ms",
            "10000",
        ],
    );
    let c = call.expect_key(T, "ok");
    assert_eq!(c["ok"], 42, "{c}");
    // File.
    let src = net.path("small.bin");
    let data = pattern_file(&src, 300_000);
    let inbox = net.path("inbox");
    let mut sink = net.probe(
        "sink",
        &["sink", "--item", "files", "--dir", inbox.to_str().unwrap()],
    );
    sink.expect_key(T, "ready");
    let mut send = net.probe(
        "send",
        &[
            "send",
            "--file",
            src.to_str().unwrap(),
            "--to",
            "probe/files",
        ],
    );
    let got = sink.expect_key(T, "received");
    assert_eq!(got["size"], 300_000);
    send.expect_key(T, "done");
    assert!(std::fs::read(inbox.join("small.bin")).unwrap() == data);
}

#[test]
fn ten_thousand_events_reach_two_subscribers_once_in_order_over_shm() {
    let net = ShmNet::new("shm_events");
    let mut subs = ready_event_subscribers(2, 10000, |n, c| net.probe(n, c));
    let mut publ = net.probe(
        "pub",
        &["ev-pub", "--item", "ev", "--count", "10000", "--subs", "2"],
    );
    let done = publ.expect_key(Duration::from_secs(60), "raised");
    assert_eq!(done["acknowledged_by_all"], 10000, "{done}");
    expect_received_in_order(&mut subs, 10000);
    // Give a duplicate the time to show up, then check none did.
    std::thread::sleep(Duration::from_millis(300));
    for s in subs.iter_mut() {
        s.terminate();
        s.wait_exit(T);
        s.drain();
        assert!(
            s.seen.iter().all(|v| v.get("extra").is_none()),
            "duplicate delivered: {:?}",
            s.seen
                .iter()
                .filter(|v| v.get("extra").is_some())
                .collect::<Vec<_>>()
        );
    }
}

/// The same as [`stream_to_a_slow_reader_loses_nothing`], over shared memory, where a pack
/// frame carries hundreds of events.
#[test]
fn a_stream_to_a_slow_reader_over_shm_waits_for_it_instead_of_dropping() {
    let net = ShmNet::new("shm_slow_reader");
    stream_to_a_slow_reader_loses_nothing(|n, c| net.probe(n, c));
}

#[test]
fn sixty_four_mb_file_arrives_bit_identical_over_shm() {
    let net = ShmNet::new("shm_file");
    let src = net.path("big.bin");
    let len = 64 << 20;
    let data = pattern_file(&src, len);
    let inbox = net.path("inbox");
    let mut sink = net.probe(
        "sink",
        &["sink", "--item", "files", "--dir", inbox.to_str().unwrap()],
    );
    sink.expect_key(T, "ready");
    let mut send = net.probe(
        "send",
        &[
            "send",
            "--file",
            src.to_str().unwrap(),
            "--to",
            "probe/files",
        ],
    );
    let got = sink.expect_key(Duration::from_secs(240), "received");
    assert_eq!(got["size"], len);
    let done = send.expect_key(T, "done");
    assert_eq!(done["attempts"], 1, "{done}");
    let out = std::fs::read(inbox.join("big.bin")).unwrap();
    assert_eq!(out.len(), data.len());
    assert!(out == data, "file differs");
}

#[test]
fn subscriber_killed_and_restarted_gets_latest_value_and_new_events() {
    let net = ShmNet::new("shm_kill9");
    // Values every 2 ms and events every 2 ms, for longer than the test needs.
    let mut vp = net.probe(
        "vpub",
        &[
            "var-pub",
            "--item",
            "position",
            "--count",
            "4000",
            "--interval-ms",
            "2",
        ],
    );
    vp.expect_key(T, "ready");
    let mut vs = net.probe("vsub", &["var-sub", "--pattern", "probe/position"]);
    let mut es = net.probe(
        "esub",
        &[
            "ev-sub",
            "--pattern",
            "probe/ev",
            "--count",
            "1000000",
            "--from-any",
        ],
    );
    es.expect_key(T, "ready");
    let mut ep = net.probe(
        "epub",
        &[
            "ev-pub",
            "--item",
            "ev",
            "--count",
            "3000",
            "--subs",
            "1",
            "--interval-ms",
            "2",
        ],
    );
    ep.expect_key(T, "subscribers");
    // Mid-stream: both subscribers are receiving.
    let before = vs.expect(T, "seq >= 100", |v| {
        v["seq"].as_u64().is_some_and(|s| s >= 100)
    })["seq"]
        .as_u64()
        .unwrap();
    es.expect_key(T, "first");
    vs.kill9();
    es.kill9();
    // The publishers go on; restarted subscribers get the latest value and new events.
    let restarted = Instant::now();
    let mut vs2 = net.probe(
        "vsub",
        &["var-sub", "--pattern", "probe/position", "--count", "1"],
    );
    let v = vs2.expect_key(T, "seq");
    assert!(
        v["seq"].as_u64().unwrap() > before,
        "restarted subscriber got {v}, older than {before} seen before the kill"
    );
    let mut es2 = net.probe(
        "esub",
        &[
            "ev-sub",
            "--pattern",
            "probe/ev",
            "--count",
            "200",
            "--from-any",
        ],
    );
    let first = es2.expect_key(T, "first")["first"].as_u64().unwrap();
    assert!(
        first > 0,
        "restarted subscriber got old events from {first}"
    );
    let r = es2.expect_key(T, "received");
    assert_eq!(r["in_order"], true, "{:?}", es2.seen);
    assert!(restarted.elapsed() < Duration::from_secs(15));
    // The publishers never blocked: every set was quick, every event was raised on schedule
    // (3000 × 2 ms plus scheduling slack), and the kill was reported as a failure, not a hang.
    let p = vp.expect_key(Duration::from_secs(60), "published");
    assert!(
        p["longest_set_us"].as_u64().unwrap() < 200_000,
        "a set blocked: {p}"
    );
    let e = ep.expect_key(Duration::from_secs(60), "raised");
    assert!(
        e["elapsed_ms"].as_u64().unwrap() < 30_000,
        "raising blocked: {e}"
    );
    assert!(
        ep.seen.iter().any(|v| v.get("failed").is_some()),
        "the killed subscriber was never reported: {:?}",
        ep.seen
    );
}

fn link_of<'a>(peers: &'a Value, node: &str) -> &'a str {
    peers["peers"]
        .as_array()
        .and_then(|a| a.iter().find(|p| p["name"] == node))
        .and_then(|p| p["link"].as_str())
        .unwrap_or_else(|| panic!("{node} not among {peers}"))
}

#[test]
fn shm_and_ethernet_node_uses_shm_for_local_peers_and_udp_for_others() {
    let net = ShmNet::new("shm_dual");
    let dual = format!("{}\n  {}", net.shm_xml(), net.ethernet_xml());
    let n = "2000";
    // A peer with shm only, one with Ethernet only, and one with both (it could be reached
    // either way: it must be reached over shm, once).
    let mut subs = [
        net.probe("s-shm", &["ev-sub", "--pattern", "probe/ev", "--count", n]),
        net.probe_with(
            "s-eth",
            &net.ethernet_xml(),
            &["ev-sub", "--pattern", "probe/ev", "--count", n],
        ),
        net.probe_with(
            "s-both",
            &dual,
            &["ev-sub", "--pattern", "probe/ev", "--count", n],
        ),
    ];
    for s in subs.iter_mut() {
        s.expect_key(T, "ready");
    }
    let mut publ = net.probe_with(
        "pub",
        &dual,
        &["ev-pub", "--item", "ev", "--count", n, "--subs", "3"],
    );
    let peers = publ.expect_key(T, "peers");
    assert_eq!(link_of(&peers, "s-shm"), "shm0", "{peers}");
    assert_eq!(link_of(&peers, "s-eth"), "ethernet0", "{peers}");
    let done = publ.expect_key(Duration::from_secs(60), "raised");
    assert_eq!(done["acknowledged_by_all"], 2000, "{done}");
    // The peer with both paths may first be heard over UDP (multicast can beat the shared-memory
    // Hello); once heard over shared memory it is reached over it, and only over it.
    assert_eq!(link_of(&done, "s-both"), "shm0", "{done}");
    assert_eq!(link_of(&done, "s-shm"), "shm0", "{done}");
    assert_eq!(link_of(&done, "s-eth"), "ethernet0", "{done}");
    for s in subs.iter_mut() {
        let r = s.expect_key(Duration::from_secs(60), "received");
        assert_eq!(r["received"], 2000, "{}", s.name);
        assert_eq!(r["in_order"], true, "{}: {:?}", s.name, s.seen);
    }
    std::thread::sleep(Duration::from_millis(500));
    for s in subs.iter_mut() {
        s.terminate();
        s.wait_exit(T);
        s.drain();
        let extra: Vec<_> = s.seen.iter().filter(|v| v.get("extra").is_some()).collect();
        assert!(extra.is_empty(), "{} got duplicates: {extra:?}", s.name);
    }
}

/// Sends `sig` (`STOP`, `CONT`) to a probe.
fn signal(p: &Proc, sig: &str) {
    let status = std::process::Command::new("kill")
        .args([&format!("-{sig}"), &p.pid().to_string()])
        .status()
        .expect("run kill");
    assert!(status.success(), "kill -{sig} {} failed", p.name);
}

#[test]
fn a_stopped_subscriber_never_blocks_a_variable_publisher() {
    let net = ShmNet::new("shm_sigstop");
    // A lease far longer than the test: the publisher keeps the stopped subscriber as a peer
    // and keeps writing into its full inbox, rather than forgetting it.
    let links = format!(
        r#"<shm service="{}" heartbeatMs="200" leaseMs="600000"/>"#,
        net.service
    );
    let mut vs = net.probe_with("vsub", &links, &["var-sub", "--pattern", "probe/position"]);
    vs.expect_key(T, "ready");
    let mut vp = net.probe_with(
        "vpub",
        &links,
        &[
            "var-pub",
            "--item",
            "position",
            "--count",
            "3000",
            "--interval-ms",
            "1",
        ],
    );
    vs.expect(T, "seq >= 50", |v| {
        v["seq"].as_u64().is_some_and(|s| s >= 50)
    });
    // The subscriber's process stops: nothing reads its inbox any more.
    signal(&vs, "STOP");
    // All 3000 sets complete while it is stopped: had a set waited for the reader, the
    // publisher could not finish before the reader resumes below.
    let p = vp.expect_key(T, "published");
    assert_eq!(p["published"], 3000, "{p}");
    signal(&vs, "CONT");
    // Reading again, the subscriber gets the newest value (older ones were overwritten).
    vs.expect(T, "seq == 2999", |v| v["seq"] == 2999);
}

/// Alive and dead iceoryx2 nodes of the shm links of `service` on this host.
fn shm_nodes(service: &str) -> (usize, usize) {
    use iceoryx2::node::NodeView;
    iceoryx2::prelude::set_log_level_from_env_or(iceoryx2::prelude::LogLevel::Error);
    use iceoryx2::prelude::{ipc_threadsafe, CallbackProgression, Node, NodeState};
    let prefix = format!("marea/{service}/");
    let ours = |d: &Option<iceoryx2::node::NodeDetails>| {
        d.as_ref()
            .is_some_and(|d| d.name().as_str().starts_with(&prefix))
    };
    let (mut alive, mut dead) = (0, 0);
    Node::<ipc_threadsafe::Service>::list(iceoryx2::config::Config::global_config(), |state| {
        match state {
            NodeState::Alive(v) if ours(v.details()) => alive += 1,
            NodeState::Dead(v) if ours(v.details()) => dead += 1,
            _ => {}
        }
        CallbackProgression::Continue
    })
    .expect("list the host's iceoryx2 nodes");
    (alive, dead)
}

#[test]
fn nodes_started_after_every_node_was_sigkilled_work_and_clear_what_was_left() {
    let net = ShmNet::new("shm_killall");
    let start = |net: &ShmNet| {
        let mut vp = net.probe("vpub", &["var-pub", "--item", "position", "--count", "1"]);
        vp.expect_key(T, "published");
        // Running until stopped, so both nodes are alive when counted.
        let mut vs = net.probe("vsub", &["var-sub", "--pattern", "probe/position"]);
        let v = vs.expect_key(T, "seq");
        assert_eq!(v["publisher"], "vpub", "{v}");
        (vp, vs)
    };
    let (mut vp, mut vs) = start(&net);
    assert_eq!(shm_nodes(&net.service), (2, 0));
    // Nobody is left to clean up after them.
    vp.kill9();
    vs.kill9();
    assert_eq!(
        shm_nodes(&net.service),
        (0, 2),
        "the killed nodes left their resources (what the next start must cope with)"
    );
    // The next start works, and removed what the killed nodes left.
    let (_vp, _vs) = start(&net);
    assert_eq!(shm_nodes(&net.service), (2, 0));
}

#[test]
fn a_file_from_shared_memory_crosses_a_gateway_onto_a_radio() {
    let net = ShmNet::new("shm_radio_file");
    // A fast radio so the file crosses in seconds; the serial link still cuts messages into
    // 300-byte packets, at most 255 per message.
    let radio = common::Radio::start(&["--air-rate", "1000000", "--full-duplex", "--seed", "23"]);
    let serial = |tty: &str| {
        format!(r#"<serial address="{tty}" baudRate="921600" heartbeatMs="500" leaseMs="5000"/>"#)
    };
    let inbox = net.path("inbox");
    let mut sink = net.probe_with(
        "sink",
        &serial(&radio.ground),
        &["sink", "--item", "files", "--dir", inbox.to_str().unwrap()],
    );
    sink.expect_key(T, "ready");
    let mut gw = net.probe_with(
        "gw",
        &format!("{}\n  {}", net.shm_xml(), serial(&radio.air)),
        &["gateway"],
    );
    let g = gw.expect_key(T, "ready");
    assert_eq!(g["gateway"], true, "{g}");
    // Larger than one shared-memory chunk may be on the radio (255 x 300 bytes): sent in
    // shared-memory-sized chunks, it could not be relayed.
    let src = net.path("plan.bin");
    let data = pattern_file(&src, 120_000);
    let mut send = net.probe(
        "send",
        &[
            "send",
            "--file",
            src.to_str().unwrap(),
            "--to",
            "probe/files",
        ],
    );
    let got = sink.expect_key(Duration::from_secs(60), "received");
    assert_eq!(got["size"], 120_000, "{got}");
    let done = send.expect_key(T, "done");
    assert_eq!(done["attempts"], 1, "{done}");
    assert!(std::fs::read(inbox.join("plan.bin")).unwrap() == data);
}
