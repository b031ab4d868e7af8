//! Nodes in separate processes whose only common medium is `usal router` (a Zenoh router, real
//! TCP, no multicast between them): they meet, read each other's variables, call each other's
//! functions, and an event stream survives the router being killed and restarted mid-stream,
//! every event arriving once, in order. And a plain Zenoh client (the official Python one) uses
//! a domain through `usal router --bridge`: JSON values, calls, `<access>` refusals.

mod common;
// The test venv's Python (made from tests/python/requirements.txt), as the MAVSDK suite finds it.
#[path = "../services/vas/tests/common/mavsdk.rs"]
mod python;

use std::path::{Path, PathBuf};
use std::time::Duration;

use common::{outcome, probe_with_config, publishing, Proc, T};
use test_support::free_tcp_port;

/// `usal --json router --listen ENDPOINT` with `extra` options, once it says it listens; and
/// what it said.
fn router_on(endpoint: &str, extra: &[String]) -> (Proc, serde_json::Value) {
    let mut args: Vec<String> = vec![
        "--json".into(),
        "router".into(),
        "--listen".into(),
        endpoint.into(),
    ];
    args.extend_from_slice(extra);
    let mut r = Proc::spawn("router", env!("CARGO_BIN_EXE_usal"), &args);
    // The first run may build usal-router: allow for it.
    let listening = r.expect(Duration::from_secs(300), "listening", |v| {
        v["event"] == "listening"
    });
    assert_eq!(listening["endpoints"][0], endpoint);
    (r, listening)
}

/// `usal router` listening on loopback `port` over plain TCP, once it says so.
fn router(port: u16) -> Proc {
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let (r, listening) = router_on(&endpoint, &[]);
    assert_eq!(
        listening["network_xml"],
        format!("<zenoh mode=\"client\" connect=\"{endpoint}\"/>").as_str()
    );
    r
}

/// A network.xml in `dir` for node `node` (namespace too) of `domain` whose only link is a
/// Zenoh client of the router at `port`.
fn network_xml(dir: &Path, node: &str, domain: &str, port: u16) -> PathBuf {
    zenoh_client_xml(
        dir,
        node,
        node,
        domain,
        &format!("tcp/127.0.0.1:{port}\""),
        "",
    )
}

#[test]
fn processes_meet_through_usal_router_and_read_variables_and_call_functions() {
    let port = free_tcp_port();
    let _router = router(port);
    let dir = tempfile::tempdir().unwrap();
    let domain = format!("zenoh-meet-{}", std::process::id());
    let air = network_xml(dir.path(), "air", &domain, port);
    let ground = network_xml(dir.path(), "ground", &domain, port);

    let _position = probe_with_config("air-pub", &air, "vas", &[], &publishing("position"));
    let _provider = probe_with_config("air-fn", &air, "vas", &[], &["provide", "--item", "double"]);
    let mut sub = probe_with_config(
        "ground-sub",
        &ground,
        "fmo",
        &[],
        &["var-sub", "--pattern", "air/vas/position", "--count", "3"],
    );
    let got = sub.expect(T, "a position from air", |v| v.get("seq").is_some());
    assert_eq!(got["name"], "air/vas/position", "{got}");
    let mut call = probe_with_config(
        "ground-call",
        &ground,
        "fmo",
        &[],
        &[
            "call",
            "--name",
            "air/vas/double",
            "--arg",
            "21",
            "--wait-ms",
            "10000",
        ],
    );
    let answer = outcome(&mut call);
    assert_eq!(answer["ok"], 42, "{answer}");
    let mut none = probe_with_config(
        "ground-none",
        &ground,
        "fmo",
        &[],
        &["call", "--name", "air/vas/nobody", "--timeout-ms", "2000"],
    );
    let refused = outcome(&mut none);
    assert_eq!(refused["error"], "no_provider", "{refused}");
}

#[test]
fn an_event_stream_survives_the_router_killed_and_restarted() {
    let port = free_tcp_port();
    let mut r = router(port);
    let dir = tempfile::tempdir().unwrap();
    let domain = format!("zenoh-restart-{}", std::process::id());
    let air = network_xml(dir.path(), "air", &domain, port);
    let ground = network_xml(dir.path(), "ground", &domain, port);
    let count = 400u64;
    let mut sub = probe_with_config(
        "ground-sub",
        &ground,
        "fmo",
        &[],
        &[
            "ev-sub",
            "--pattern",
            "air/probe/ev",
            "--count",
            &count.to_string(),
        ],
    );
    sub.expect_key(T, "ready");
    // 400 events 10 ms apart: the stream is still running when the router dies.
    let mut publ = probe_with_config(
        "air-pub",
        &air,
        "probe",
        &[],
        &[
            "ev-pub",
            "--item",
            "ev",
            "--count",
            &count.to_string(),
            "--subs",
            "1",
            "--interval-ms",
            "10",
        ],
    );
    publ.expect_key(T, "peers");
    // A second into the four-second stream (the fault's timing, not a synchronisation), the
    // router dies; it is down for a second, then back on the same port.
    std::thread::sleep(Duration::from_secs(1));
    r.kill9();
    // Still streaming when the router died, or the test would prove nothing.
    assert!(
        publ.try_expect(Duration::ZERO, |v| v.get("raised").is_some())
            .is_none(),
        "the stream ended before the router was killed"
    );
    std::thread::sleep(Duration::from_secs(1));
    let _r = router(port);
    let done = publ.expect_key(Duration::from_secs(60), "raised");
    assert_eq!(done["failed_raises"], 0, "{done}");
    assert_eq!(done["acknowledged_by_all"], count, "{done}");
    let received = sub.expect_key(Duration::from_secs(60), "received");
    assert_eq!(received["received"], count, "{received}");
    assert_eq!(received["in_order"], true, "{:?}", sub.seen);
}

/// A network.xml in `dir` for node `node` of `namespace` in `domain` whose one link is a Zenoh
/// client with `connect` (the endpoint, its closing quote and further attributes), holding
/// `inner` too.
fn zenoh_client_xml(
    dir: &Path,
    node: &str,
    namespace: &str,
    domain: &str,
    connect: &str,
    inner: &str,
) -> PathBuf {
    let path = dir.join(format!("{node}.xml"));
    std::fs::write(
        &path,
        format!(
            r#"<network node="{node}" namespace="{namespace}" domain="{domain}">
  <zenoh name="wan" mode="client" connect="{connect}/>
  {inner}
</network>
"#
        ),
    )
    .expect("write network.xml");
    path
}

/// `tests/python/SCRIPT` run by `py` with `args`.
fn python_script(py: &Path, script: &str, args: &[String]) -> Proc {
    let path = python::repo_root().join("tests/python").join(script);
    let args: Vec<String> = std::iter::once(path.display().to_string())
        .chain(args.iter().cloned())
        .collect();
    Proc::spawn("python", py.to_str().expect("a UTF-8 path"), &args)
}

/// The identity tests' router (`usal router` on `endpoint` with `args`, bridging through the
/// node of `bridge`), once it bridges with identities guest, node and pilot.
fn bridging_router(endpoint: &str, args: &[String], bridge: &Path) -> Proc {
    let args: Vec<String> = args
        .iter()
        .cloned()
        .chain(["--bridge".into(), bridge.display().to_string()])
        .collect();
    let (mut router, _) = router_on(endpoint, &args);
    let bridging = router.expect(T, "bridging", |v| v["event"] == "bridging");
    assert_eq!(
        bridging["identities"],
        serde_json::json!(["guest", "node", "pilot"]),
        "{bridging}"
    );
    router
}

/// Node `airfn` (its network.xml `xml`) providing `airfn/vas/change_state`, which its
/// `<access>` lets only `zenoh/pilot` call; once it provides it.
fn guarded_change_state(xml: impl Fn(&str, &str, &str) -> PathBuf) -> Proc {
    let airfn = xml(
        "airfn",
        "airfn",
        r#"<access trustClaims="yes"><allow kind="call" item="airfn/vas/change_state" from="zenoh/pilot"/></access>"#,
    );
    let mut guarded = probe_with_config(
        "airfn",
        &airfn,
        "vas",
        &[],
        &["provide", "--item", "change_state"],
    );
    guarded.expect_key(T, "ready");
    guarded
}

/// The official Zenoh client for Python (`eclipse-zenoh`, no USAL code), logged in to the
/// router as a user, reads a vehicle's position as JSON (its stream and its last value), sees
/// the domain's nodes as liveliness tokens, and calls a function with a JSON argument. The
/// guarded `change_state`, whose `<access>` rule lets only `zenoh/pilot` call it: `denied` on
/// its plain key (anonymous), served when pilot calls as itself; `denied` to guest calling as
/// itself; and guest calling under pilot's key gets nothing at all (the router drops it).
#[test]
fn a_python_zenoh_client_reads_json_and_calls_through_the_bridge_as_itself() {
    let Some(py) = python::python() else {
        return;
    };
    let port = free_tcp_port();
    let dir = tempfile::tempdir().unwrap();
    let domain = format!("zenoh-py-{}", std::process::id());
    // Every session logs in: the nodes as `node`, the Python client as pilot, then guest.
    let users = dir.path().join("users.txt");
    std::fs::write(&users, "node:node-pw\npilot:pilot-pw\nguest:guest-pw\n").unwrap();
    let login = dir.path().join("node.json5");
    std::fs::write(
        &login,
        r#"{transport: {auth: {usrpwd: {user: "node", password: "node-pw"}}}}"#,
    )
    .unwrap();
    let connect = format!("tcp/127.0.0.1:{port}\" config=\"{}\"", login.display());
    let xml = |node: &str, namespace: &str, inner: &str| {
        zenoh_client_xml(dir.path(), node, namespace, &domain, &connect, inner)
    };
    let endpoint = format!("tcp/127.0.0.1:{port}");
    let _router = bridging_router(
        &endpoint,
        &["--users".into(), users.display().to_string()],
        &xml("bridge", "zbridge", ""),
    );

    let air = xml("air", "air", "");
    let airdbl = xml("airdbl", "air", "");
    let _position = probe_with_config(
        "air",
        &air,
        "vas",
        &[],
        &[&publishing("position")[..], &["--usal-type"]].concat(),
    );
    let mut double = probe_with_config(
        "airdbl",
        &airdbl,
        "vas",
        &[],
        &["provide", "--item", "double"],
    );
    double.expect_key(T, "ready");
    let _guarded = guarded_change_state(xml);

    let mut client = python_script(
        &py,
        "zenoh_client.py",
        &[
            endpoint,
            domain.clone(),
            "pilot:pilot-pw".into(),
            "guest:guest-pw".into(),
        ],
    );
    let nodes = client.expect_key(T, "nodes");
    for n in ["air", "airdbl", "airfn", "bridge"] {
        assert!(
            nodes["nodes"]
                .as_array()
                .is_some_and(|a| a.iter().any(|x| x == n)),
            "{n} missing from {nodes}"
        );
    }
    let position = client.expect_key(T, "position");
    assert_eq!(position["encoding"], "application/json", "{position}");
    assert!(
        position["position"]["lat"]
            .as_f64()
            .is_some_and(|l| (l - 41.275).abs() < 0.01),
        "{position}"
    );
    assert_eq!(position["position"]["speed"], 1.5, "{position}");
    let last = client.expect_key(T, "last");
    assert!(last["last"]["lat"].is_number(), "{last}");
    let doubled = client.expect_key(T, "double");
    assert_eq!(doubled["double"], 42, "{doubled}");
    let anonymous = client.expect_key(T, "change_state");
    assert_eq!(anonymous["change_state"]["error"], "denied", "{anonymous}");
    let pilot = client.expect_key(T, "as_self");
    assert_eq!(pilot["as_self"]["served"], 2, "{pilot}");
    let guest = client.expect_key(T, "other_as_self");
    assert_eq!(
        guest["other_as_self"]["refused"]["error"], "denied",
        "{guest}"
    );
    let impersonation = client.expect_key(T, "impersonation");
    assert_eq!(
        impersonation["impersonation"]["refused"]["error"], "no reply",
        "{impersonation}"
    );
    client.expect_key(T, "done");
}

/// Mutual TLS: `usal router --tls-dir D --tls-client NAME` makes a certificate for each
/// client, and the router knows each by its certificate's name. The Python client presenting
/// pilot's calls `change_state` as pilot (served: the `<access>` rule names `zenoh/pilot`);
/// presenting guest's it is denied as guest, and under pilot's key it gets nothing (the router
/// drops it).
#[test]
fn a_client_known_by_its_certificate_calls_as_itself() {
    let Some(py) = python::python() else {
        return;
    };
    let port = free_tcp_port();
    let dir = tempfile::tempdir().unwrap();
    let domain = format!("zenoh-mtls-{}", std::process::id());
    let tls = dir.path().join("tls");
    let client = |name: &str| tls.join("clients").join(format!("{name}.json5"));
    let endpoint = format!("tls/127.0.0.1:{port}");
    let connect = format!("{endpoint}\" config=\"{}\"", client("node").display());
    let xml = |node: &str, namespace: &str, inner: &str| {
        zenoh_client_xml(dir.path(), node, namespace, &domain, &connect, inner)
    };
    let mut args: Vec<String> = vec!["--tls-dir".into(), tls.display().to_string()];
    for name in ["node", "pilot", "guest"] {
        args.extend(["--tls-client".into(), name.into()]);
    }
    let _router = bridging_router(&endpoint, &args, &xml("bridge", "zbridge", ""));
    let _guarded = guarded_change_state(xml);

    let call = |who: &str, as_whom: &str, listen_s: &str| {
        let mut p = python_script(
            &py,
            "zenoh_call.py",
            &[
                client(who).display().to_string(),
                endpoint.clone(),
                format!("usal/{domain}/@as/{as_whom}/airfn/vas/change_state"),
                "1".into(),
                listen_s.into(),
            ],
        );
        p.expect(T * 2, "an answer", |_| true)
    };
    let pilot = call("pilot", "pilot", "15");
    assert_eq!(pilot["ok"], 2, "{pilot}");
    let guest = call("guest", "guest", "15");
    assert_eq!(guest["err"]["error"], "denied", "{guest}");
    let impersonation = call("guest", "pilot", "3");
    assert_eq!(impersonation["none"], true, "{impersonation}");
}

/// `usal router --tls-dir` makes the deployment's certificates and serves TLS: nodes given the
/// client configuration it wrote (trusting its authority) meet through it; a node that does not
/// trust the authority cannot even open its link, and says why.
#[test]
fn nodes_meet_over_tls_with_the_routers_certificates_and_others_cannot_join() {
    let port = free_tcp_port();
    let dir = tempfile::tempdir().unwrap();
    let tls = dir.path().join("tls");
    let endpoint = format!("tls/127.0.0.1:{port}");
    let (router, listening) =
        router_on(&endpoint, &["--tls-dir".into(), tls.display().to_string()]);
    let client = tls.join("client.json5");
    assert_eq!(
        listening["network_xml"],
        format!(
            "<zenoh mode=\"client\" connect=\"{endpoint}\" config=\"{}\"/>",
            client.display()
        )
        .as_str()
    );
    let domain = format!("zenoh-tls-{}", std::process::id());
    let trusted = format!(r#"config="{}""#, client.display());
    let xml = |node: &str, extra: &str| {
        let path = dir.path().join(format!("{node}.xml"));
        std::fs::write(
            &path,
            format!(
                r#"<network node="{node}" namespace="{node}" domain="{domain}">
  <zenoh mode="client" connect="{endpoint}" {extra}/>
</network>"#
            ),
        )
        .unwrap();
        path
    };
    let publisher = probe_with_config(
        "air",
        &xml("air", &trusted),
        "vas",
        &[],
        &publishing("position"),
    );
    let mut sub = probe_with_config(
        "ground",
        &xml("ground", &trusted),
        "fmo",
        &[],
        &["var-sub", "--pattern", "air/vas/position", "--count", "1"],
    );
    let got = sub.expect(T, "a position over TLS", |v| v.get("seq").is_some());
    assert_eq!(got["name"], "air/vas/position", "{got}");
    // Zenoh's TLS link reads and writes one connection from two tasks (zenoh#2557): on two
    // threads that corrupted it and crashed routers under load. The router and the nodes run
    // Zenoh's I/O on one thread (its `app` runtime), with no `rx-*`/`tx-*` threads of its own.
    for (what, pid) in [("router", router.pid()), ("node", publisher.pid())] {
        let names: Vec<String> = std::fs::read_dir(format!("/proc/{pid}/task"))
            .unwrap()
            .filter_map(|t| std::fs::read_to_string(t.ok()?.path().join("comm")).ok())
            .map(|n| n.trim().to_owned())
            .collect();
        assert!(
            names.iter().any(|n| n.starts_with("app-"))
                && !names
                    .iter()
                    .any(|n| n.starts_with("rx-") || n.starts_with("tx-")),
            "{what}'s threads: {names:?}"
        );
    }

    // No trust in the authority (and a short wait for the router, to fail soon).
    let untrusting = dir.path().join("untrusting.json5");
    std::fs::write(
        &untrusting,
        r#"{ mode: "client", scouting: { multicast: { enabled: false } }, connect: { timeout_ms: 2000 } }"#,
    )
    .unwrap();
    let mut intruder = probe_with_config(
        "intruder",
        &xml("intruder", &format!(r#"config="{}""#, untrusting.display())),
        "x",
        &[],
        &["var-sub", "--pattern", "air/vas/position", "--count", "1"],
    );
    let status = intruder.wait_exit(T);
    assert!(!status.success(), "a node without the authority joined");
    assert!(intruder.seen.is_empty(), "{:?}", intruder.seen);
}
