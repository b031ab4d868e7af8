//! Gateways: a ground LAN and an air LAN, each with its own discovery group, joined over a
//! serial radio (`marea-radio`, real ptys) by one gateway node on each side. Every node is a
//! separate process. The two LANs must behave as one system for all four primitives, and the
//! ground gateway must serve a late subscriber the last value it forwarded without the radio.

mod common;

use std::path::Path;
use std::time::Duration;

use common::{Proc, Radio};
use serde_json::Value;

/// Generous bound for anything that crosses the radio (declarations, then data).
const RADIO: Duration = Duration::from_secs(60);

/// One LAN's discovery settings for the probes (their built-in loopback Ethernet config).
struct Lan {
    domain: String,
    port: u16,
}

impl Lan {
    fn probe(&self, node: &str, namespace: &str, cmd: &[&str]) -> Proc {
        let mut args = vec!["--namespace", namespace];
        args.extend_from_slice(cmd);
        self.probe_outside_namespaces(node, &args)
    }

    /// A probe in no namespace (its items' names are as given).
    fn probe_outside_namespaces(&self, node: &str, cmd: &[&str]) -> Proc {
        let mut args: Vec<String> = [
            "--node",
            node,
            "--domain",
            &self.domain,
            "--mcast-port",
            &self.port.to_string(),
            "--heartbeat-ms",
            "200",
            "--lease-ms",
            "1500",
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        args.extend(cmd.iter().map(|s| s.to_string()));
        Proc::spawn(node, env!("CARGO_BIN_EXE_marea-probe"), &args)
    }

    /// A gateway: this LAN plus the radio at `baud`, from a network.xml written into `dir`.
    fn gateway(&self, dir: &Path, node: &str, namespace: &str, tty: &str, baud: u32) -> Proc {
        let xml = format!(
            r#"<network node="{node}" namespace="{namespace}" domain="{domain}">
  {lan}
  <serial name="radio" address="{tty}" baudRate="{baud}" heartbeatMs="1000" leaseMs="15000"/>
</network>"#,
            domain = self.domain,
            lan = self.ethernet("lan"),
        );
        spawn_gateway(dir, node, &xml)
    }

    /// This LAN's `<ethernet>`, named `name`.
    fn ethernet(&self, name: &str) -> String {
        format!(
            r#"<ethernet name="{name}" bind="127.0.0.1:0" multicast="239.255.77.1:{port}" interface="127.0.0.1"
            heartbeatMs="200" leaseMs="1500"/>"#,
            port = self.port
        )
    }
}

/// A gateway between two LANs (both in `a`'s domain), from a network.xml written into `dir`
/// (`gateway="true"`: two Ethernet links alone do not make a node forward).
fn lan_gateway(dir: &Path, node: &str, a: &Lan, b: &Lan) -> Proc {
    let xml = format!(
        r#"<network node="{node}" namespace="lab" domain="{domain}" gateway="true">
  {a}
  {b}
</network>"#,
        domain = a.domain,
        a = a.ethernet("lan-a"),
        b = b.ethernet("lan-b"),
    );
    spawn_gateway(dir, node, &xml)
}

/// `marea-probe gateway` with the network.xml `xml`, written into `dir`.
fn spawn_gateway(dir: &Path, node: &str, xml: &str) -> Proc {
    let path = dir.join(format!("{node}.xml"));
    std::fs::write(&path, xml).expect("write network.xml");
    let args = vec![
        "--config".to_owned(),
        path.display().to_string(),
        "gateway".to_owned(),
    ];
    Proc::spawn(node, env!("CARGO_BIN_EXE_marea-probe"), &args)
}

fn forwarded(v: &Value, name: &str, cached: bool) -> bool {
    v["forwarded"].as_array().is_some_and(|items| {
        items
            .iter()
            .any(|i| i["name"] == name && (!cached || i["cached"] == true))
    })
}

/// Two LANs on this host (same domain, their own discovery groups on ports `base` and
/// `base + 1`, so only the gateways join them), the radio between them started with
/// `radio_args`, and a ready gateway on each side, its serial link at `baud`.
struct Joined {
    ground: Lan,
    air: Lan,
    dir: tempfile::TempDir,
    radio: Radio,
    air_gw: Proc,
    ground_gw: Proc,
}

impl Joined {
    fn start(test: &str, base: u16, radio_args: &[&str], baud: u32) -> Joined {
        let domain = format!("{test}-{}", std::process::id());
        let ground = Lan {
            domain: domain.clone(),
            port: base,
        };
        let air = Lan {
            domain,
            port: base + 1,
        };
        let dir = tempfile::tempdir().expect("temp dir");
        let radio = Radio::start(radio_args);
        let mut air_gw = air.gateway(dir.path(), "air-gw", "rover1", &radio.air, baud);
        let mut ground_gw = ground.gateway(dir.path(), "ground-gw", "ground", &radio.ground, baud);
        for gw in [&mut air_gw, &mut ground_gw] {
            let v = gw.expect_key(RADIO, "ready");
            assert_eq!(
                v["gateway"], true,
                "{}: a LAN + radio node forwards",
                gw.name
            );
        }
        Joined {
            ground,
            air,
            dir,
            radio,
            air_gw,
            ground_gw,
        }
    }
}

/// Base of a test's two discovery ports (each test takes two from `offset`).
fn base_port(offset: u16) -> u16 {
    test_support::multicast_port(u64::from(std::process::id())) + offset
}

#[test]
fn two_lans_joined_by_a_radio_behave_as_one_system() {
    let Joined {
        ground,
        air,
        dir,
        radio,
        mut air_gw,
        mut ground_gw,
    } = Joined::start(
        "gateway",
        base_port(0),
        &["--loss", "0.001", "--corrupt", "0.001", "--seed", "21"],
        57_600,
    );

    // Air LAN: two services (a vehicle publishing and providing; a payload accepting files).
    let sink_dir = dir.path().join("received");
    std::fs::create_dir_all(&sink_dir).expect("sink dir");
    let mut vehicle = air.probe("vehicle", "rover1", &["provide", "--item", "double"]);
    vehicle.expect_key(RADIO, "ready");
    let mut position = air.probe(
        "position",
        "rover1",
        &["var-pub", "--item", "position", "--count", "1"],
    );
    position.expect_key(RADIO, "published");
    let sink_arg = sink_dir.display().to_string();
    let mut payload = air.probe(
        "payload",
        "rover1",
        &["sink", "--item", "plans", "--dir", &sink_arg],
    );
    payload.expect_key(RADIO, "ready");

    // Ground LAN: two services following and commanding the vehicle.
    let mut monitor = ground.probe(
        "monitor",
        "ground",
        // Stays subscribed (count 0): the gateways forward, and cache, while someone listens.
        &["var-sub", "--pattern", "rover1/**", "--count", "0"],
    );
    monitor.expect_key(RADIO, "ready");
    let v = monitor.expect_key(RADIO, "seq");
    assert_eq!(v["name"], "rover1/probe/position", "{v}");
    assert_eq!(
        v["publisher"], "position",
        "the sample names its real publisher: {v}"
    );

    // Events, air -> ground, exactly once and in order, end to end through both gateways.
    let mut alarms_sub = ground.probe(
        "alarms-sub",
        "ground",
        &[
            "ev-sub",
            "--pattern",
            "rover1/probe/alarm",
            "--count",
            "200",
        ],
    );
    alarms_sub.expect_key(RADIO, "ready");
    let mut alarms = air.probe(
        "alarms",
        "rover1",
        &["ev-pub", "--item", "alarm", "--count", "200", "--subs", "1"],
    );
    let done = alarms_sub.expect_key(RADIO, "received");
    assert_eq!(done["received"], 200, "{done}");
    assert_eq!(done["in_order"], true, "{done}");
    let raised = alarms.expect_key(RADIO, "raised");
    assert_eq!(raised["acknowledged_by_all"], 200, "{raised}");

    // A call ground -> air through both gateways, and its answer back.
    let mut caller = ground.probe(
        "caller",
        "ground",
        &[
            "call",
            "--name",
            "rover1/probe/double",
            "--arg",
            "21",
            "--timeout-ms",
            "20000",
            "--wait-ms",
            "60000",
        ],
    );
    let v = caller.expect(RADIO, "ok or error", |v| {
        v.get("ok").is_some() || v.get("error").is_some()
    });
    assert_eq!(v["ok"], 42, "{v}");
    vehicle.expect(RADIO, "the call", |v| v["called"] == 21);

    // A file ground -> air: chunks relayed by both gateways, acknowledged end to end.
    let content: Vec<u8> = (0..60_000u32).map(|i| (i * 7 % 251) as u8).collect();
    let plan = dir.path().join("plan.bin");
    std::fs::write(&plan, &content).expect("write file");
    let plan_arg = plan.display().to_string();
    let mut sender = ground.probe(
        "sender",
        "ground",
        &["send", "--file", &plan_arg, "--to", "rover1/probe/plans"],
    );
    let v = sender.expect(RADIO, "done or an error", |v| {
        v.get("done").is_some() || v.get("error").is_some()
    });
    assert_eq!(v["done"], 60_000, "{v}");
    let got = payload.expect_key(RADIO, "received");
    let path = got["received"].as_str().expect("path");
    assert_eq!(
        std::fs::read(path).expect("read"),
        content,
        "file bit-identical"
    );

    // The ground gateway keeps the position it forwarded: with the radio frozen, a new
    // subscriber on the ground LAN still gets it at once, from the gateway's cache.
    ground_gw.expect(RADIO, "the cached position", |v| {
        forwarded(v, "rover1/probe/position", true)
    });
    radio.freeze();
    let mut late = ground.probe(
        "late",
        "ground",
        &[
            "var-sub",
            "--pattern",
            "rover1/probe/position",
            "--count",
            "1",
        ],
    );
    let v = late.expect_key(Duration::from_secs(10), "seq");
    radio.resume();
    assert_eq!(v["name"], "rover1/probe/position", "{v}");
    assert_eq!(v["publisher"], "position", "{v}");

    for p in [
        &mut late,
        &mut sender,
        &mut caller,
        &mut alarms,
        &mut alarms_sub,
        &mut monitor,
        &mut payload,
        &mut position,
        &mut vehicle,
        &mut ground_gw,
        &mut air_gw,
    ] {
        p.terminate();
    }
    // Nothing was delivered twice: the event subscriber reports any extra event it gets.
    alarms_sub.drain();
    assert!(
        !alarms_sub.seen.iter().any(|v| v.get("extra").is_some()),
        "duplicate events: {:?}",
        alarms_sub.seen
    );
}

/// A stream forwarded from a LAN onto the radio is held to the radio's pace: the air gateway
/// counts the events it forwarded that the ground gateway has not acknowledged, and while more
/// than a stream's window on the radio (4 s of its line: 192 of these 5-byte events at 2,400
/// baud) wait, it tells the LAN's nodes it is behind (`Flow`), and the publisher's stream
/// waits. The radio carries ~8 such events a second and the publisher sends one a millisecond,
/// so 200 events end within half a second without flow control (the gateway queueing the rest
/// for the radio, as it did) and only once the radio carried about half of them with it
/// (~12 s); all arrive, in order.
#[test]
fn a_stream_forwarded_onto_the_radio_is_held_to_the_radio_s_pace() {
    let j = Joined::start(
        "gateway-flow",
        base_port(2),
        &["--air-rate", "2400", "--seed", "5"],
        2_400,
    );
    let mut sub = j.ground.probe(
        "stream-sub",
        "ground",
        &["ev-sub", "--pattern", "rover1/probe/ev", "--count", "200"],
    );
    sub.expect_key(RADIO, "ready");
    let mut publ = j.air.probe(
        "streamer",
        "rover1",
        &[
            "ev-pub",
            "--item",
            "ev",
            "--count",
            "200",
            "--subs",
            "1",
            "--stream",
            "--interval-ms",
            "1",
        ],
    );
    let raised = publ.expect_key(Duration::from_secs(120), "raised");
    assert_eq!(raised["lost_events"], 0, "{raised}");
    let elapsed = raised["elapsed_ms"].as_u64().expect("elapsed_ms");
    assert!(
        elapsed >= 5_000,
        "the stream ended after {elapsed} ms, before the radio could carry much of it: {raised}"
    );
    let got = sub.expect_key(Duration::from_secs(120), "received");
    assert_eq!(got["received"], 200, "{got}");
    assert_eq!(got["in_order"], true, "{got}");
}

/// `n` LANs in a row, in one domain, on discovery ports `base`.., joined by a ready gateway
/// between each two (written into `dir`): the gateways, kept alive by the caller, and the LANs.
fn lans_in_a_row(test: &str, base: u16, n: u16, dir: &Path) -> (Vec<Proc>, Vec<Lan>) {
    let domain = format!("{test}-{}", std::process::id());
    let lans: Vec<Lan> = (0..n)
        .map(|i| Lan {
            domain: domain.clone(),
            port: base + i,
        })
        .collect();
    let gateways = lans
        .windows(2)
        .enumerate()
        .map(|(i, pair)| {
            let mut gw = lan_gateway(dir, &format!("gw{i}"), &pair[0], &pair[1]);
            let v = gw.expect_key(RADIO, "ready");
            assert_eq!(v["gateway"], true, "two LANs and gateway=\"true\" forward");
            gw
        })
        .collect();
    (gateways, lans)
}

/// Spawns probe `node` on the first of `lans` if it is the publisher (`pub`), else on the
/// last: only gateways join them.
fn across<'a>(lans: &'a [Lan]) -> impl Fn(&str, &[&str]) -> Proc + 'a {
    move |node, cmd| {
        let lan = if node == "pub" {
            &lans[0]
        } else {
            &lans[lans.len() - 1]
        };
        lan.probe_outside_namespaces(node, cmd)
    }
}

/// A reader slower than the links behind a gateway (two LANs, one gateway node between them):
/// its node tells the gateway its readers are behind (`Flow`), the gateway, which forwards the
/// stream to it, passes that on to the publisher, and the stream of 150,000 events waits for
/// the reader instead of its mailbox (65,536) dropping them: all arrive, in order, none lost.
/// (Before the gateway passed it on, the reader saw a gap and the publisher reported nothing.)
#[test]
fn a_stream_to_a_slow_reader_behind_a_gateway_loses_nothing() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (_gateways, lans) = lans_in_a_row("gateway-slow", base_port(4), 2, dir.path());
    common::stream_to_a_slow_reader_loses_nothing(across(&lans));
}

/// The same two gateways away (three LANs in a row), with a reader five times slower (a
/// millisecond's pause every 20 events): the nearer gateway tells the farther one that
/// readers one gateway beyond it are behind, and that one tells the publisher. (Told only by
/// a reader's own node, the publisher was held back only when the gateways happened to lag,
/// and the reader lost events.)
#[test]
fn a_stream_to_a_slow_reader_two_gateways_away_loses_nothing() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (_gateways, lans) = lans_in_a_row("gateway-slow2", base_port(6), 3, dir.path());
    let spawn = across(&lans);
    let mut sub = common::event_reader(&spawn, "sub", 100_000, &["--slow", "20"]);
    let mut publ = common::event_streamer(&spawn, "pub", 100_000);
    common::expect_stream_finished(&mut publ);
    common::expect_received_in_order(std::slice::from_mut(&mut sub), 100_000);
}

/// Streams both ways across two gateways (three LANs in a row), to a slow reader at each end:
/// each gateway forwards events to the other and hears from it that readers beyond it are
/// behind. A plain "behind" passed back and forth would keep each gateway behind because the
/// other is, and hold both streams for ever (the hop count and never telling a state back to
/// where it came from prevent it); both streams end, every event in order.
#[test]
fn streams_both_ways_across_two_gateways_to_slow_readers_both_end() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (_gateways, lans) = lans_in_a_row("gateway-both", base_port(9), 3, dir.path());
    let ends = [(&lans[0], "a", "c"), (&lans[2], "c", "a")];
    let count = "50000";
    let mut subs: Vec<Proc> = ends
        .iter()
        .map(|(lan, me, _)| {
            let pattern = format!("probe/to_{me}");
            let args = [
                "ev-sub",
                "--pattern",
                &pattern,
                "--count",
                count,
                "--slow",
                "20",
            ];
            let mut sub = lan.probe_outside_namespaces(&format!("sub-{me}"), &args);
            sub.expect_key(RADIO, "ready");
            sub
        })
        .collect();
    let mut pubs: Vec<Proc> = ends
        .iter()
        .map(|(lan, me, other)| {
            let item = format!("to_{other}");
            let args = [
                "ev-pub", "--item", &item, "--count", count, "--subs", "1", "--stream",
            ];
            lan.probe_outside_namespaces(&format!("pub-{me}"), &args)
        })
        .collect();
    for p in &mut pubs {
        common::expect_stream_finished(p);
    }
    common::expect_received_in_order(&mut subs, 50_000);
}

/// A reader already behind when a gateway first forwards events to it: a publisher on its
/// own LAN keeps it behind (it is held back directly), then a publisher beyond the gateway
/// starts a stream to it. The gateway had heard that the reader's node is behind before it
/// forwarded anything there; it passes that on as soon as it does, so the far stream waits
/// too and the reader's mailbox drops nothing. (When the gateway kept a node's state only
/// once it forwarded to it, the far stream ran unchecked until the reader's state next
/// changed, and the reader lost events.)
#[test]
fn a_reader_already_behind_when_a_gateway_first_forwards_to_it_loses_nothing() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (_gateways, lans) = lans_in_a_row("gateway-late", base_port(12), 2, dir.path());
    let (far, near) = (&lans[0], &lans[1]);
    let (near_count, far_count) = (100_000, 50_000);
    let total = (near_count + far_count).to_string();
    let mut sub = near.probe_outside_namespaces(
        "sub",
        &[
            "ev-sub",
            "--pattern",
            "probe/ev",
            "--count",
            &total,
            "--slow",
            "20",
        ],
    );
    sub.expect_key(RADIO, "ready");
    let stream = |lan: &Lan, name: &str, count: u64| {
        let count = count.to_string();
        lan.probe_outside_namespaces(
            name,
            &[
                "ev-pub", "--item", "ev", "--count", &count, "--subs", "1", "--stream",
            ],
        )
    };
    let mut near_pub = stream(near, "pub-near", near_count);
    sub.expect_key(RADIO, "behind");
    let mut far_pub = stream(far, "pub-far", far_count);
    common::expect_stream_finished(&mut far_pub);
    common::expect_stream_finished(&mut near_pub);
    common::expect_received_in_order(std::slice::from_mut(&mut sub), near_count + far_count);
}

/// Probe `service` of node `air` (namespace `rover1`) on `lan` running `cmd`, from a
/// network.xml written into `dir` whose `<access>` holds `rule`; ready.
fn guarded_air(dir: &Path, lan: &Lan, rule: &str, service: &str, cmd: &[&str]) -> Proc {
    let xml = format!(
        r#"<network node="air" namespace="rover1" domain="{domain}">
  {lan}
  <access trustClaims="yes">
    {rule}
  </access>
</network>"#,
        domain = lan.domain,
        lan = lan.ethernet("lan"),
    );
    let path = dir.join("air.xml");
    std::fs::write(&path, xml).expect("write network.xml");
    let mut probe = common::probe_with_config(service, &path, service, &[], cmd);
    probe.expect_key(RADIO, "ready");
    probe
}

/// `node` of `namespace` on `lan` calls `rover1/vas/retask` with `arg` once it sees the
/// provider.
fn call_retask(lan: &Lan, node: &str, namespace: &str, arg: u64) -> Proc {
    lan.probe(
        node,
        namespace,
        &[
            "call",
            "--name",
            "rover1/vas/retask",
            "--arg",
            &arg.to_string(),
            "--wait-ms",
            "20000",
            "--timeout-ms",
            "20000",
        ],
    )
}

/// A call through a gateway is the caller's, not the gateway's: the provider's `<access>`
/// rules (`ground/*` may call) see the node that called across the gateway (`lab/gw0`,
/// which no rule names, relays it), so the `ground` nodes are served and `evil/fmo` denied;
/// and three callers behind the gateway, calling a function that takes 1.5 s at about the
/// same time, are all served. (Before, every call through the gateway was denied, as the
/// gateway's.) That each caller has lanes of its own, so that none supersedes another's
/// call however they overlap, is pinned by the unit test
/// `node::call::tests::calls_a_gateway_relays_are_checked_and_laned_as_their_callers`.
#[test]
fn calls_through_a_gateway_are_checked_and_queued_as_their_callers() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (_gateways, lans) = lans_in_a_row("gateway-call", base_port(14), 2, dir.path());
    let (ground, air) = (&lans[0], &lans[1]);
    let mut vas = guarded_air(
        dir.path(),
        air,
        r#"<allow kind="call" item="rover1/vas/*" from="ground/*"/>"#,
        "vas",
        &["provide", "--item", "retask", "--delay-ms", "1500"],
    );
    let mut intruder = call_retask(ground, "fmo", "evil", 13);
    let denied = common::outcome_within(&mut intruder, RADIO);
    assert_eq!(denied["error"], "denied", "{denied}");
    let mut callers: Vec<Proc> = (1..=3)
        .map(|i| call_retask(ground, &format!("fmo{i}"), "ground", i))
        .collect();
    for (i, caller) in (1u64..).zip(&mut callers) {
        let got = common::outcome_within(caller, RADIO);
        assert_eq!(got["ok"], 2 * i, "{}: {got}", caller.name);
    }
    let mut ran: Vec<u64> = (0..3)
        .map(|_| {
            vas.expect_key(RADIO, "called")["called"]
                .as_u64()
                .unwrap_or(0)
        })
        .collect();
    ran.sort_unstable();
    assert_eq!(ran, [1, 2, 3], "the denied call (13) never ran");
}

/// A file through a gateway is its sender's: the sink's `<access>` (`ground/*` may send to
/// `rover1/fpma/plans`) sees the node that sent it across the gateway, so `ground/fpmo`'s plan
/// is stored (and named as the file's sender) and `evil/fpmo`'s denied (before, both were
/// denied, as the gateway's).
#[test]
fn a_file_through_a_gateway_is_checked_as_its_sender_s() {
    let dir = tempfile::tempdir().expect("temp dir");
    let (_gateways, lans) = lans_in_a_row("gateway-file", base_port(16), 2, dir.path());
    let (ground, air) = (&lans[0], &lans[1]);
    let inbox = dir.path().join("plans");
    std::fs::create_dir_all(&inbox).expect("inbox");
    let mut fpma = guarded_air(
        dir.path(),
        air,
        r#"<allow kind="file" item="rover1/fpma/plans" from="ground/*"/>"#,
        "fpma",
        &[
            "sink",
            "--item",
            "plans",
            "--dir",
            &inbox.display().to_string(),
        ],
    );
    let send = |namespace: &str, file: &str| {
        let plan = dir.path().join(file);
        std::fs::write(&plan, format!("<plan from=\"{namespace}\"/>")).expect("plan");
        let plan = plan.display().to_string();
        let mut sender = ground.probe(
            "fpmo",
            namespace,
            &common::sending(&plan, "rover1/fpma/plans", "30"),
        );
        common::outcome_within(&mut sender, RADIO)
    };
    let refused = send("evil", "evil.xml");
    assert_eq!(refused["error"], "denied", "{refused}");
    let sent = send("ground", "plan.xml");
    assert!(sent.get("done").is_some(), "{sent}");
    let stored = fpma.expect_key(RADIO, "received");
    assert!(stored.to_string().contains("plan.xml"), "{stored}");
    assert_eq!(
        stored["from"], "fpmo",
        "the sender, not the gateway: {stored}"
    );
    assert!(
        !inbox.join("evil.xml").exists(),
        "the denied file was stored"
    );
}

/// A call that waits behind a saturated 57600-baud radio, through the two gateways that join
/// it to the LANs, loses that wait from its caller's remaining time: one its caller has
/// already reported as timed out reaches the provider with no time left and is never run,
/// and a newer call issued after it is run and answered.
#[test]
fn a_call_its_caller_gave_up_on_behind_a_saturated_radio_never_runs() {
    let j = Joined::start(
        "gateway-expiry",
        base_port(18),
        &["--air-rate", "57600", "--seed", "9"],
        57_600,
    );
    let mut vas = j
        .air
        .probe("vas", "rover1", &["provide", "--item", "retask"]);
    vas.expect_key(RADIO, "ready");
    let call = |node: &str, arg: u64, timeout_ms: u64| {
        j.ground.probe(
            node,
            "ground",
            &[
                "call",
                "--name",
                "rover1/probe/retask",
                "--arg",
                &arg.to_string(),
                "--wait-ms",
                "30000",
                "--timeout-ms",
                &timeout_ms.to_string(),
            ],
        )
    };
    // The provider is known on the ground before the radio fills up.
    let mut first = call("fmo0", 1, 30_000);
    assert_eq!(common::outcome_within(&mut first, RADIO)["ok"], 2);
    assert_eq!(vas.expect_key(RADIO, "called")["called"], 1);

    // A stream of events from the ground to the air fills the ground gateway's radio queue
    // (seconds of line time: a call behind it took 11-14 s).
    let mut sub = j.air.probe(
        "flood-sub",
        "rover1",
        &["ev-sub", "--pattern", "ground/probe/ev", "--count", "20000"],
    );
    sub.expect_key(RADIO, "ready");
    let mut flood = j.ground.probe(
        "flood",
        "ground",
        &[
            "ev-pub", "--item", "ev", "--count", "20000", "--subs", "1", "--stream",
        ],
    );
    flood.expect_key(RADIO, "subscribers");

    let mut late = call("fmo1", 2, 300);
    let gave_up = common::outcome_within(&mut late, RADIO);
    assert_eq!(gave_up["error"], "timeout", "{gave_up}");
    let mut newer = call("fmo2", 3, 120_000);
    let answered = common::outcome_within(&mut newer, Duration::from_secs(150));
    assert_eq!(answered["ok"], 6, "{answered}");
    // The provider ran the newer call and never the one its caller had given up on.
    let ran = vas.expect_key(RADIO, "called");
    assert_eq!(
        ran["called"], 3,
        "the call timed out at its caller ran at the provider: {ran}"
    );
}
