//! The flight log, end to end with real processes: `usal run` of the rover demo writes a flight
//! log holding every record kind; `usal replay` of that log is seen by a marea subscriber and
//! by an FPMo station joined to the replay's domain; a corrupt or cut log is refused naming its
//! line.

#[path = "../services/fmo/tests/common/mod.rs"]
mod common;

use std::io::Write;
use std::path::Path;
use std::process::Stdio;
use std::time::Duration;

use flightplan::api::{PlanEvent, PlanEventKind};
use marea::config::{EthernetConfig, LinkConfig};
use marea::{NetworkConfig, Node};
use serde_json::Value;
use tokio::process::Command;
use usal_types::FlightState;

const USAL: &str = env!("CARGO_BIN_EXE_usal");
/// Bound on a whole run of the demo plan (about 10 s at --speedup 20 on an idle machine).
const FLIGHT: Duration = Duration::from_secs(180);
/// Bound on a replay at --speed 5 of a ~10 s flight, discovery included.
const REPLAY: Duration = Duration::from_secs(60);

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// Builds the services `usal run` starts into the directory holding `usal` (this test's
/// target directory): the one build every test that starts services asks for.
fn build_services() {
    common::workspace_bin("vas");
}

/// Every record of a gzip flight log, the header first.
fn read_log(path: &Path) -> Vec<Value> {
    let file = std::fs::File::open(path).expect("the log exists");
    let text = std::io::read_to_string(flate2::read::GzDecoder::new(file)).expect("gzip");
    text.lines()
        .map(|l| serde_json::from_str(l).expect("each line is JSON"))
        .collect()
}

/// A node joined like `usal --domain DOMAIN --mcast-port PORT` joins.
fn net(node: &str, domain: &str, port: u16) -> NetworkConfig {
    let mut c = NetworkConfig::ethernet_loopback(node);
    c.domain = domain.to_owned();
    c.links = vec![LinkConfig::Ethernet(EthernetConfig {
        interface: std::net::Ipv4Addr::LOCALHOST,
        multicast: std::net::SocketAddrV4::new(std::net::Ipv4Addr::new(239, 255, 77, 1), port),
        ..EthernetConfig::default()
    })];
    c
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_run_writes_a_log_of_each_kind_and_its_replay_is_seen_by_a_subscriber() {
    build_services();
    let dir = tempfile::tempdir().expect("tempdir");
    let log = dir.path().join("flight.jsonl.gz");
    let run = Command::new(USAL)
        .args([
            "--json",
            "run",
            "config/missions/rover-demo.xml",
            "--until-complete",
        ])
        .args(["--speedup", "20", "--log"])
        .arg(&log)
        .current_dir(root())
        .stdin(Stdio::null())
        .kill_on_drop(true)
        .output();
    let out = tokio::time::timeout(FLIGHT, run)
        .await
        .expect("usal run ends in time")
        .expect("usal run starts");
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}\n{stdout}\n{}",
        out.status,
        String::from_utf8_lossy(&out.stderr)
    );
    // The path is said at the start and after the summary.
    let lines: Vec<Value> = stdout
        .lines()
        .filter_map(|l| serde_json::from_str(l).ok())
        .collect();
    let at = |event: &str| lines.iter().position(|v| v["event"] == event);
    let (first, summary, last) = (
        at("flight_log").expect("the log's path at the start"),
        at("summary").expect("a summary"),
        at("flight_log_written").expect("the log's path at the end"),
    );
    assert!(first < summary && summary < last, "{stdout}");
    assert_eq!(lines[last]["path"], log.display().to_string());

    let records = read_log(&log);
    let header = &records[0];
    assert_eq!(header["format"], "usal-flight-log");
    assert_eq!(header["version"], 1);
    assert_eq!(header["mission"], "rover-demo");
    assert_eq!(records.last().unwrap()["kind"], "end");
    for kind in ["telemetry", "state", "plan", "link", "command", "note"] {
        assert!(
            records.iter().any(|r| r["kind"] == kind),
            "no {kind} record in the log"
        );
    }
    let named = |name: &'static str| records.iter().filter(move |r| r["name"] == name);
    assert!(named("rover1/vas/position").count() > 5);
    assert!(named("rover1/vas/flight_state").any(|r| r["value"] == "WAYPOINT_NAVIGATION"));
    // The plan upload is a command with its answer.
    assert!(named("rover1/fpma/plans")
        .any(|r| r["kind"] == "command" && r["answer"]["receiver"].is_string()));
    // Times never go back down the file, whichever task wrote a record.
    let ts: Vec<f64> = records[1..]
        .iter()
        .filter_map(|r| r["t"].as_f64())
        .collect();
    assert_eq!(ts.len(), records.len() - 1, "a record without t");
    assert!(ts.windows(2).all(|w| w[1] >= w[0]), "{ts:?}");
    // Every command the vehicle received is there, with who sent it and the answer: here the
    // station's Start.
    let start = named("rover1/vas/commands")
        .find(|r| r["value"]["command"] == "change_state")
        .unwrap_or_else(|| panic!("no change_state in rover1/vas/commands"));
    assert_eq!(start["kind"], "command", "{start}");
    assert!(
        start["value"]["from"]
            .as_str()
            .is_some_and(|f| f.starts_with("gcs/"))
            && start["value"]["ok"] == true
            && start["value"]["args"] == "WaypointNavigation",
        "{start}"
    );
    // The air side kept its own log beside the ground's: states, the command, mission traffic.
    let air = std::fs::read_to_string(dir.path().join("flight.air/air/vas-air.jsonl"))
        .expect("the air node's VAS log beside the flight log");
    let air: Vec<Value> = air
        .lines()
        .map(|l| serde_json::from_str(l).expect("an air log line is JSON"))
        .collect();
    assert_eq!(air[0]["format"], "usal-air-log");
    assert!(air
        .iter()
        .any(|r| r["kind"] == "state" && r["to"] == "WAYPOINT_NAVIGATION"));
    assert!(air.iter().any(|r| r["kind"] == "command"
        && r["command"] == "change_state"
        && r["from"] == start["value"]["from"]));
    assert!(air
        .iter()
        .any(|r| r["kind"] == "mission" && r["op"] == "push" && r["ok"] == true));
    let reached_in_log = named("rover1/fpma/plan_event")
        .filter(|r| r["value"]["kind"]["WaypointReached"].is_object())
        .count();
    assert!(reached_in_log >= 10, "{reached_in_log}");

    // Replay into a fresh domain; a subscriber there sees the flight again.
    let domain = format!("replay-{}", std::process::id());
    // The stations' default discovery port, so the FPMo below finds the replay too.
    let port = 7477;
    let node = Node::open(&net("replay-watcher", &domain, port))
        .await
        .expect("node");
    let svc = node.service("watcher").expect("service");
    let states = svc
        .subscribe_variable::<FlightState>("rover1/vas/flight_state")
        .expect("subscribe");
    let events = svc
        .subscribe_event::<PlanEvent>("rover1/fpma/plan_event")
        .expect("subscribe");
    // And a flight-plan station, as a pilot reviewing the flight would open one.
    let fpmo_bin = Path::new(USAL).with_file_name("fpmo").display().to_string();
    let fpmo = common::Station::start(&fpmo_bin, "FPMO_URL", &["--domain", &domain]).await;
    let fmo_bin = Path::new(USAL).with_file_name("fmo").display().to_string();
    let fmo = common::Station::start(&fmo_bin, "FMO_URL", &["--domain", &domain]).await;
    let mut replay = Command::new(USAL)
        .args(["--domain", &domain, "--mcast-port", &port.to_string()])
        .args(["replay", "--speed", "5"])
        .arg(&log)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .expect("usal replay starts");
    let mut replay_out = replay.stdout.take().expect("piped");
    let shown = tokio::spawn(async move {
        let mut text = String::new();
        let _ = tokio::io::AsyncReadExt::read_to_string(&mut replay_out, &mut text).await;
        text
    });
    let watch = async {
        let (mut seen_states, mut reached) = (Vec::new(), 0usize);
        loop {
            tokio::select! {
                s = states.recv() => {
                    let s = s.expect("states").value;
                    if seen_states.last() != Some(&s) {
                        seen_states.push(s);
                    }
                }
                e = events.recv() => {
                    match e.expect("events").value.kind {
                        PlanEventKind::WaypointReached { .. } => reached += 1,
                        PlanEventKind::PlanCompleted => return (seen_states, reached),
                        _ => {}
                    }
                }
            }
        }
    };
    let (seen_states, reached) = tokio::time::timeout(REPLAY, watch)
        .await
        .expect("the replayed plan completes at the subscriber");
    // Both stations say it is a replay, of which mission, while it plays.
    for (station, name) in [(&fpmo, "FPMo"), (&fmo, "FMo")] {
        let s = station
            .wait_state(&format!("REPLAY in the {name}"), |s| {
                s["replay"]["live"] == true && s["replay"]["mission"] == "rover-demo"
            })
            .await;
        assert!(
            s["replay"]["duration_s"].as_f64().is_some_and(|d| d > 1.0),
            "{}",
            s["replay"]
        );
    }
    assert!(
        seen_states.contains(&FlightState::WaypointNavigation),
        "{seen_states:?}"
    );
    assert_eq!(reached, reached_in_log);
    let status = tokio::time::timeout(REPLAY, replay.wait())
        .await
        .expect("usal replay ends")
        .expect("status");
    assert!(status.success(), "{status}");
    // The replay shows the vehicle's own log with the ground's: the Start as the VAS took it.
    let shown = shown.await.expect("the replay's output");
    assert!(
        shown.contains("with the air-side logs of air:")
            && shown.contains("air air: command from gcs/")
            && shown.contains("change_state(WaypointNavigation) -> ok"),
        "{shown}"
    );
    // The FPMo drew the replayed flight: the plan, the track, its completion.
    let s = fpmo
        .wait_state("the replayed plan completed in the FPMo", |s| {
            common::vehicle(s, "rover1").is_some_and(|v| {
                v["plan_name"] == "rover-demo" && v["progress"]["value"]["completed"] == true
            })
        })
        .await;
    let v = common::vehicle(&s, "rover1").expect("rover1");
    assert!(v["track"].as_array().is_some_and(|t| t.len() > 5), "{v:#}");
    // Its end is said too, so the stations do not show a link that died.
    fmo.wait_state("the replay's end in the FMo", |s| {
        s["replay"]["ended"] == true
    })
    .await;
    fpmo.kill().await;
    fmo.kill().await;
    node.shutdown().await;
}

/// Runs `usal replay` on `log` and returns (success, stderr).
async fn replay_of(log: &Path) -> (bool, String) {
    let out = Command::new(USAL)
        .args(["--domain", &format!("bad-log-{}", std::process::id())])
        .args([
            "--mcast-port",
            &test_support::free_udp_port().to_string(),
            "--wait-ms",
            "0",
        ])
        .args(["replay", "--speed", "100"])
        .arg(log)
        .kill_on_drop(true)
        .output();
    let out = tokio::time::timeout(REPLAY, out)
        .await
        .expect("usal replay ends")
        .expect("usal replay starts");
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn gz(path: &Path, text: &str) {
    let f = std::fs::File::create(path).expect("create");
    let mut w = flate2::write::GzEncoder::new(f, flate2::Compression::default());
    w.write_all(text.as_bytes()).expect("write");
    w.finish().expect("finish");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_corrupt_or_cut_log_is_refused_naming_its_line() {
    let dir = tempfile::tempdir().expect("tempdir");
    let header = r#"{"format":"usal-flight-log","version":1,"mission":"m","started_utc":"2026-01-01T00:00:00Z"}"#;
    let good = r#"{"t":0.1,"kind":"state","item":"variable","name":"rover1/vas/flight_state","type":"usal_types::FlightState","raw":"01"}"#;

    let corrupt = dir.path().join("corrupt.jsonl.gz");
    gz(
        &corrupt,
        &format!("{header}\n{good}\n{{\"t\": 0.2, \"kind\n{good}\n"),
    );
    let (ok, err) = replay_of(&corrupt).await;
    assert!(
        !ok && err.contains("line 3") && err.contains("not JSON"),
        "{err}"
    );

    let bad_raw = dir.path().join("bad-raw.jsonl");
    std::fs::write(
        &bad_raw,
        format!("{header}\n{good}\n{}\n", good.replace("\"01\"", "\"0x\"")),
    )
    .expect("write");
    let (ok, err) = replay_of(&bad_raw).await;
    assert!(
        !ok && err.contains("line 3") && err.contains("hex"),
        "{err}"
    );

    let newer = dir.path().join("newer.jsonl");
    std::fs::write(
        &newer,
        header.replace("\"version\":1", "\"version\":9") + "\n",
    )
    .expect("write");
    let (ok, err) = replay_of(&newer).await;
    assert!(!ok && err.contains("version 9"), "{err}");

    // A log cut short, as a killed run leaves it: the gzip stream ends early.
    let body: String = (0..400)
        .map(|i| format!("{}\n", good.replace("0.1", &format!("{}.0", i))))
        .collect();
    let whole = dir.path().join("whole.jsonl.gz");
    gz(&whole, &format!("{header}\n{body}"));
    let bytes = std::fs::read(&whole).expect("read");
    let cut = dir.path().join("cut.jsonl.gz");
    std::fs::write(&cut, &bytes[..bytes.len() - 12]).expect("write");
    let (ok, err) = replay_of(&cut).await;
    assert!(
        !ok && err.contains("truncated or corrupt after line"),
        "{err}"
    );
    assert!(err.contains("--partial"), "{err}");
}
