//! The middleware's primitives across real processes on 127.0.0.1 (each node is a
//! `marea-probe` child process).

mod common;

use std::time::Duration;

use common::{
    event_reader, event_streamer, expect_received_in_order, expect_stream_finished,
    ready_event_subscribers, stream_to_a_slow_reader_loses_nothing, Net, Proc, T,
};

#[test]
fn late_joiner_gets_the_last_value_at_once() {
    let net = Net::new("late_joiner");
    let mut publ = net.probe("pub", &["var-pub", "--item", "position", "--count", "5"]);
    publ.expect_key(T, "published");
    // The subscriber starts after every value was published: it must get the last one (seq 4)
    // without any new publication.
    let mut sub = net.probe(
        "sub",
        &["var-sub", "--pattern", "probe/position", "--count", "1"],
    );
    let v = sub.expect_key(T, "seq");
    assert_eq!(v["seq"], 4, "late joiner got {v}");
    assert_eq!(v["publisher"], "pub");
    assert_eq!(v["name"], "probe/position");
}

#[test]
fn wildcard_subscription_follows_a_fleet() {
    let net = Net::new("fleet");
    let mut r1 = net.probe_ns(
        "r1",
        "rover1",
        &["var-pub", "--item", "position", "--count", "1"],
    );
    let mut r2 = net.probe_ns(
        "r2",
        "rover2",
        &["var-pub", "--item", "position", "--count", "1"],
    );
    r1.expect_key(T, "published");
    r2.expect_key(T, "published");
    let mut station = net.probe(
        "gs",
        &["var-sub", "--pattern", "*/probe/position", "--count", "2"],
    );
    let a = station.expect_key(T, "seq");
    let b = station.expect_key(T, "seq");
    let mut names = vec![
        a["name"].as_str().unwrap().to_owned(),
        b["name"].as_str().unwrap().to_owned(),
    ];
    names.sort();
    assert_eq!(
        names,
        vec!["rover1/probe/position", "rover2/probe/position"]
    );
}

#[test]
fn link_health_is_published_as_variables_a_station_can_follow() {
    let net = Net::new("link_health");
    let mut rover = net.probe_ns(
        "r1",
        "rover1",
        &["var-pub", "--item", "position", "--count", "1"],
    );
    rover.expect_key(T, "published");
    // A typed wildcard over everything: the rover's position (another type) must be skipped
    // silently, and the rover's link health must arrive with its peer and its traffic counted.
    let mut station = net.probe("gs", &["health", "--pattern", "**", "--count", "6"]);
    let mut rover_link = None;
    for _ in 0..6 {
        let v = station.expect(T, "a value or an error", |v| {
            v.get("name").is_some() || v.get("error").is_some()
        });
        assert!(v.get("error").is_none(), "typed wildcard reported {v}");
        if v["name"] == "rover1/link/ethernet0/stats" && v["out_bps"].as_f64() > Some(0.0) {
            rover_link = Some(v);
        }
    }
    let v = rover_link.expect("the rover's link health with traffic within six values");
    assert_eq!(v["publisher"], "r1");
    assert_eq!(v["link"], "ethernet0");
    assert!(v["peers"].as_u64() >= Some(1), "{v}");
}

#[test]
fn ten_thousand_events_reach_three_subscribers_exactly_once_in_order() {
    let net = Net::new("events_3x10k");
    let mut subs = ready_event_subscribers(3, 10000, |n, c| net.probe(n, c));
    let mut publ = net.probe(
        "pub",
        &["ev-pub", "--item", "ev", "--count", "10000", "--subs", "3"],
    );
    let done = publ.expect_key(Duration::from_secs(60), "raised");
    assert_eq!(done["acknowledged_by_all"], 10000, "{done}");
    expect_received_in_order(&mut subs, 10000);
    // Exactly once: no subscriber printed an out-of-order (duplicate) line.
    for s in &subs {
        assert!(s.seen.iter().all(|v| v.get("out_of_order").is_none()));
    }
}

/// Two subscribers of `probe/ev`, `victim` (never done) and `keeper` (3,000 events), and a
/// publisher of 3,000 events, one per ms, sent as `mode` says (`--window N` or `--stream`). The
/// victim is killed mid-stream, once it has received events and more are in flight. Returns the
/// publisher's first `key` line, how long after the kill it came, the publisher and the keeper.
fn kill_one_of_two_subscribers(
    net: &Net,
    mode: &[&str],
    key: &str,
) -> (serde_json::Value, Duration, Proc, Proc) {
    let mut victim = net.probe(
        "victim",
        &["ev-sub", "--pattern", "probe/ev", "--count", "100000000"],
    );
    let mut keeper = net.probe(
        "keeper",
        &["ev-sub", "--pattern", "probe/ev", "--count", "3000"],
    );
    victim.expect_key(T, "ready");
    keeper.expect_key(T, "ready");
    let mut args = vec![
        "ev-pub",
        "--item",
        "ev",
        "--count",
        "3000",
        "--subs",
        "2",
        "--interval-ms",
        "1",
    ];
    args.extend_from_slice(mode);
    let mut publ = net.probe("pub", &args);
    publ.expect_key(T, "subscribers");
    victim.expect_key(T, "first");
    victim.kill9();
    let killed_at = std::time::Instant::now();
    let line = publ.expect_key(T, key);
    (line, killed_at.elapsed(), publ, keeper)
}

#[test]
fn killed_subscriber_fails_pending_events_by_name_and_publisher_goes_on() {
    let net = Net::new("kill_sub");
    let (failed, waited, mut publ, mut keeper) =
        kill_one_of_two_subscribers(&net, &["--window", "64"], "failed");
    assert!(
        failed["failed"].as_str().unwrap().starts_with("victim/"),
        "{failed}"
    );
    assert!(
        failed["reason"].as_str().unwrap().contains("victim"),
        "{failed}"
    );
    // When: once the victim's lease ran out, which the node's unit test checks on paused time
    // (`a_silent_peer_is_dropped_when_its_lease_runs_out_and_not_before`); here the wall clock
    // of a shared machine only bounds it (`T`).
    eprintln!("failure reported {waited:?} after the kill");
    // The publisher keeps working: the other subscriber gets every event in order.
    let r = keeper.expect_key(Duration::from_secs(60), "received");
    assert_eq!(r["received"], 3000);
    assert_eq!(r["in_order"], true);
    publ.expect_key(T, "raised");
}

/// `Event::stream` is lossless with back-pressure and no report per event: 100,000 events reach
/// two subscriber processes exactly once and in order, and the publisher's flush returns once
/// both acknowledged all of them.
#[test]
fn a_stream_of_100k_events_reaches_two_subscribers_exactly_once_in_order() {
    let net = Net::new("stream_2x100k");
    let mut subs = ready_event_subscribers(2, 100000, |n, c| net.probe(n, c));
    let mut publ = net.probe(
        "pub",
        &[
            "ev-pub", "--item", "ev", "--count", "100000", "--subs", "2", "--stream",
        ],
    );
    let done = publ.expect_key(Duration::from_secs(120), "raised");
    assert_eq!(done["lost_events"], 0, "{done}");
    expect_received_in_order(&mut subs, 100000);
    for s in &subs {
        assert!(s.seen.iter().all(|v| v.get("out_of_order").is_none()));
    }
    assert!(
        publ.seen.iter().all(|v| v.get("lost").is_none()),
        "{:?}",
        publ.seen
    );
}

/// [`stream_to_a_slow_reader_loses_nothing`] over UDP.
#[test]
fn a_stream_to_a_slow_reader_waits_for_it_instead_of_dropping() {
    let net = Net::new("stream_slow_reader");
    stream_to_a_slow_reader_loses_nothing(|n, c| net.probe(n, c));
}

/// A callback subscriber (`Service::subscribe_event_with`) in its own process takes a stream
/// as it arrives and holds it back when slow: its callback sleeps a millisecond every 100
/// events on the link's receive task, and the stream of 150,000 events waits for its
/// acknowledgements instead of losing any (all arrive in order, no loss reported).
#[test]
fn a_stream_to_a_slow_callback_subscriber_loses_nothing() {
    let net = Net::new("stream_slow_callback");
    let spawn = |n: &str, c: &[&str]| net.probe(n, c);
    let mut sub = event_reader(&spawn, "sub", 150000, &["--callback", "--slow", "100"]);
    let mut publ = event_streamer(&spawn, "pub", 150000);
    expect_stream_finished(&mut publ);
    expect_received_in_order(std::slice::from_mut(&mut sub), 150000);
}

/// A publisher that comes while a subscriber's node is behind is told so too: a second stream,
/// started once a slow reader (20,000 events/s) has over a quarter of its mailbox waiting from the
/// first, waits as well (untold, it would overfill the mailbox at once), and the reader gets
/// all 2 × 100,000 events, in order per publisher, none dropped.
#[test]
fn a_publisher_joining_while_a_reader_is_behind_waits_too() {
    let net = Net::new("stream_slow_join");
    let spawn = |n: &str, c: &[&str]| net.probe(n, c);
    let mut sub = event_reader(&spawn, "sub", 200000, &["--slow", "20"]);
    let mut first = event_streamer(&spawn, "pub1", 100000);
    sub.expect_key(T, "behind");
    let mut second = event_streamer(&spawn, "pub2", 100000);
    expect_stream_finished(&mut first);
    expect_stream_finished(&mut second);
    expect_received_in_order(std::slice::from_mut(&mut sub), 200000);
}

/// A reader that stops holds no stream back for good: once it has taken nothing for 200 ms its
/// node stops saying it is behind, the stream to it runs to its end (its mailbox drops the
/// oldest events at its bound, as for any reader that stopped), instead of waiting forever.
#[test]
fn a_stream_to_a_reader_that_stopped_goes_on() {
    let net = Net::new("stream_stopped_reader");
    let spawn = |n: &str, c: &[&str]| net.probe(n, c);
    let mut sub = event_reader(&spawn, "sub", 1000, &["--then-stop"]);
    let mut publ = event_streamer(&spawn, "pub", 150000);
    expect_received_in_order(std::slice::from_mut(&mut sub), 1000);
    expect_stream_finished(&mut publ);
}

/// A stream's subscriber killed mid-stream: the stream reports the events that node did not
/// acknowledge, naming it, within its lease, and goes on: the other subscriber gets every
/// event in order.
#[test]
fn killed_subscriber_of_a_stream_is_reported_by_name_and_the_stream_goes_on() {
    let net = Net::new("stream_kill");
    let (lost, waited, mut publ, mut keeper) =
        kill_one_of_two_subscribers(&net, &["--stream"], "lost");
    assert_eq!(lost["lost"], "victim", "{lost}");
    assert!(lost["events"].as_u64() >= Some(1), "{lost}");
    assert!(
        lost["reason"].as_str().is_some_and(|r| !r.is_empty()),
        "{lost}"
    );
    // When: see `killed_subscriber_fails_pending_events_by_name_and_publisher_goes_on`.
    eprintln!("loss reported {waited:?} after the kill");
    let r = keeper.expect_key(Duration::from_secs(60), "received");
    assert_eq!(r["received"], 3000);
    assert_eq!(r["in_order"], true);
    let done = publ.expect_key(Duration::from_secs(60), "raised");
    assert_eq!(done["raised"], 3000, "{done}");
}

#[test]
fn calls_fail_distinctly_no_provider_timeout_remote_error() {
    let net = Net::new("calls");
    // Nobody provides it: fails fast.
    let mut c = net.probe(
        "c0",
        &["call", "--name", "probe/nothing", "--timeout-ms", "5000"],
    );
    let r = c.expect_key(T, "error");
    assert_eq!(r["error"], "no_provider");
    assert!(r["ms"].as_u64().unwrap() < 1000, "{r}");

    let mut slow = net.probe(
        "slow",
        &[
            "--service",
            "slowsvc",
            "provide",
            "--item",
            "f",
            "--delay-ms",
            "3000",
        ],
    );
    slow.expect_key(T, "ready");
    let mut c = net.probe(
        "c1",
        &[
            "call",
            "--name",
            "slowsvc/f",
            "--timeout-ms",
            "300",
            "--wait-ms",
            "5000",
        ],
    );
    let r = c.expect_key(T, "error");
    assert_eq!(r["error"], "timeout", "{r}");

    let mut bad = net.probe(
        "bad",
        &[
            "--service",
            "badsvc",
            "provide",
            "--item",
            "f",
            "--fail",
            "battery too low",
        ],
    );
    bad.expect_key(T, "ready");
    let mut c = net.probe("c2", &["call", "--name", "badsvc/f", "--wait-ms", "5000"]);
    let r = c.expect_key(T, "error");
    assert_eq!(r["error"], "remote", "{r}");
    assert!(
        r["message"].as_str().unwrap().contains("battery too low"),
        "{r}"
    );

    let mut good = net.probe("good", &["--service", "goodsvc", "provide", "--item", "f"]);
    good.expect_key(T, "ready");
    let mut c = net.probe(
        "c3",
        &[
            "call",
            "--name",
            "goodsvc/f",
            "--arg",
            "21",
            "--wait-ms",
            "5000",
        ],
    );
    assert_eq!(c.expect_key(T, "ok")["ok"], 42);
}

#[test]
fn provider_killed_mid_call_yields_link_lost() {
    let net = Net::new("call_lost");
    let mut slow = net.probe(
        "slow",
        &[
            "--service",
            "slowsvc",
            "provide",
            "--item",
            "f",
            "--delay-ms",
            "30000",
        ],
    );
    slow.expect_key(T, "ready");
    let mut c = net.probe(
        "c",
        &[
            "call",
            "--name",
            "slowsvc/f",
            "--timeout-ms",
            "20000",
            "--wait-ms",
            "5000",
        ],
    );
    // Kill the provider while the call is in its handler.
    slow.expect_key(T, "called");
    slow.kill9();
    let r = c.expect_key(T, "error");
    assert_eq!(r["error"], "link_lost", "{r}");
    assert!(r["message"].as_str().unwrap().contains("slow"), "{r}");
}

#[test]
fn wrong_payload_type_is_refused_with_a_clear_error() {
    let net = Net::new("wrong_type");
    let mut publ = net.probe("pub", &["var-pub", "--item", "position", "--count", "1"]);
    publ.expect_key(T, "published");
    let mut sub = net.probe("sub", &["var-sub-string", "--pattern", "probe/position"]);
    let r = sub.expect_key(T, "error");
    let msg = r["error"].as_str().unwrap();
    assert!(msg.contains("probe/position"), "{msg}");
    assert!(msg.contains("Position"), "{msg}");
    assert!(msg.contains("String"), "{msg}");
    assert!(
        sub.seen.iter().all(|v| v.get("value").is_none()),
        "garbage delivered"
    );
}

#[test]
fn twenty_mb_file_arrives_identical_and_resumes_after_receiver_restart() {
    let net = Net::new("file_20mb");
    let dir = tempfile::tempdir().unwrap();
    let src = dir.path().join("payload.bin");
    let data: Vec<u8> = (0..20_000_000u32)
        .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
        .collect();
    std::fs::write(&src, &data).unwrap();
    let inbox = dir.path().join("inbox");
    let inbox_s = inbox.to_str().unwrap();

    let mut rx = net.probe("rx", &["sink", "--item", "files", "--dir", inbox_s]);
    rx.expect_key(T, "ready");
    let mut tx = net.probe(
        "tx",
        &[
            "send",
            "--file",
            src.to_str().unwrap(),
            "--to",
            "probe/files",
        ],
    );
    // Kill the receiver once some progress was acknowledged, before the end.
    tx.expect(T, "progress >= 10", |v| {
        v["progress"]
            .as_u64()
            .is_some_and(|p| (10..90).contains(&p))
    });
    rx.kill9();
    let mut rx2 = net.probe("rx", &["sink", "--item", "files", "--dir", inbox_s]);
    let got = rx2.expect_key(Duration::from_secs(90), "received");
    let done = tx.expect_key(Duration::from_secs(30), "done");
    assert_eq!(got["size"], 20_000_000);
    let resumed = got["resumed_from"].as_u64().unwrap();
    assert!(resumed > 0, "receiver did not resume: {got}");
    let sent = done["sent"].as_u64().unwrap();
    assert!(
        sent - 20_000_000 < 20_000_000,
        "re-sent {} bytes, not fewer than the whole file",
        sent - 20_000_000
    );
    assert_eq!(done["attempts"], 2);
    let out = std::fs::read(inbox.join("payload.bin")).unwrap();
    assert!(out == data, "file differs");
    // No temp file left behind: the inbox holds the file and the sink's private directory of
    // partial files, which is empty.
    let mut leftovers: Vec<_> = std::fs::read_dir(&inbox)
        .unwrap()
        .flatten()
        .map(|e| e.file_name())
        .collect();
    leftovers.sort();
    assert_eq!(leftovers, [".partial", "payload.bin"], "{leftovers:?}");
    let parts: Vec<_> = std::fs::read_dir(inbox.join(".partial"))
        .unwrap()
        .flatten()
        .map(|e| e.file_name())
        .collect();
    assert!(parts.is_empty(), "{parts:?}");
}

/// A subscriber process that stops acknowledging (stopped, then killed) with 4,096 events in
/// flight towards it: every one of them completes, with an error naming it, as soon as its
/// lease runs out, not one waits longer.
#[test]
fn killed_subscriber_with_4096_raises_in_flight_completes_every_one_at_once() {
    let net = Net::new("kill_sub_4096");
    let mut victim = net.probe(
        "victim",
        &["ev-sub", "--pattern", "probe/ev", "--count", "100000000"],
    );
    let ready = victim.expect_key(T, "ready");
    let pid = ready["pid"]
        .as_u64()
        .expect("ev-sub prints its pid")
        .to_string();
    let mut publ = net.probe(
        "pub",
        &[
            "ev-pub", "--item", "ev", "--count", "300000", "--subs", "1", "--window", "4096",
        ],
    );
    publ.expect_key(T, "subscribers");
    victim.expect_key(T, "first");
    // Stop it: it acknowledges nothing more, so the publisher's window fills.
    let stopped = std::process::Command::new("kill")
        .args(["-STOP", &pid])
        .status()
        .expect("run kill -STOP");
    assert!(stopped.success());
    let stall = publ.expect_key(T, "stalled");
    assert_eq!(stall["stalled"], 4096, "{stall}");
    victim.kill9();
    let killed_at = std::time::Instant::now();
    let failed = publ.expect_key(T, "failed");
    assert!(
        failed["failed"].as_str().unwrap().starts_with("victim/"),
        "{failed}"
    );
    assert!(
        failed["reason"].as_str().unwrap().contains("victim"),
        "{failed}"
    );
    // Every pending raise completed once the lease ran out (the ones raised after it have no
    // subscriber and complete at once): the publisher finishes the rest soon after.
    let done = publ.expect_key(Duration::from_secs(60), "raised");
    let waited = killed_at.elapsed();
    assert!(
        done["failed_raises"].as_u64() >= Some(4096),
        "not all pending raises failed: {done}"
    );
    let raised_so_far = stall["raised_so_far"].as_u64().unwrap();
    assert_eq!(
        done["acknowledged_by_all"].as_u64().unwrap() + done["failed_raises"].as_u64().unwrap(),
        300_000,
        "{done}"
    );
    assert!(raised_so_far >= 4096, "{stall}");
    let failed_ms = failed["after_ms"].as_u64().unwrap();
    let last_ms = done["last_failed_ms"].as_u64().unwrap();
    // All of them together: the last failure came right after the first, not after a timeout
    // of its own (generous bound: a debug build on a loaded machine).
    assert!(
        last_ms.saturating_sub(failed_ms) < 1_000,
        "first failure at {failed_ms} ms, last at {last_ms} ms"
    );
    // When the lease ran out is the node's unit test's (on paused time); here `T` bounds it.
    eprintln!("done {waited:?} after the kill: {done}");
}

/// `usal send FILE SINK` (the sink named positionally, as `call` and `echo` name theirs) says
/// how a send ended, every time: 0 once the sink stored the file (six sends in
/// a row, where a race between the progress and the outcome once made most of them say "node is
/// shutting down" after the sink had stored them), 1 naming the domain when no node offers the
/// sink.
#[test]
fn usal_send_exits_0_once_stored_and_1_naming_the_domain_without_a_sink() {
    let net = Net::new("usal_send");
    let dir = tempfile::tempdir().expect("tempdir");
    let inbox = dir.path().join("inbox");
    let mut sink = net.probe_ns(
        "air",
        "rover1",
        &[
            "sink",
            "--item",
            "plans",
            "--dir",
            inbox.to_str().expect("UTF-8"),
        ],
    );
    sink.expect_key(T, "ready");
    let file = dir.path().join("plan.xml");
    std::fs::write(&file, "<flightPlan/>").expect("write the file");
    let usal = |to: &str| {
        std::process::Command::new(env!("CARGO_BIN_EXE_usal"))
            .args([
                "--domain",
                &net.domain,
                "--mcast-port",
                &net.port.to_string(),
            ])
            .args(["send", file.to_str().expect("UTF-8"), to])
            .args(["--retry-secs", "10"])
            .output()
            .expect("usal send")
    };
    for i in 0..6 {
        let out = usal("rover1/probe/plans");
        assert!(
            out.status.success(),
            "send {i}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert!(
            String::from_utf8_lossy(&out.stdout).contains("to air"),
            "{out:?}"
        );
        sink.expect_key(T, "received");
    }
    let out = usal("rover1/probe/nothing");
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("no file sink 'rover1/probe/nothing'")
            && err.contains(&format!("in domain {}", net.domain)),
        "{err}"
    );
}
