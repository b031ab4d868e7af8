//! FMo manual control end to end over the radio: `usal run` of the rover radio mission (its air
//! and ground nodes joined only by `marea-radio` at 57600 baud with byte errors, a gateway on
//! each side) without its plan-following station; from the ground FMo's HTTP API the pilot
//! takes MANUAL_NAVIGATION and drives with the throttle as the page posts it: mavsim's rover
//! moves forward (its position, telemetry back over the radio), and stops when the dead-man is
//! released. The run's flight log holds the manual control and the state.

#[path = "../services/fmo/tests/common/mod.rs"]
mod common;

use std::path::Path;
use std::process::Stdio;
use std::time::Duration;

use common::{command, request_with, vehicle};
use serde_json::{json, Value};
use tokio::io::{AsyncBufReadExt, BufReader};
use tokio::process::Command;

const USAL: &str = env!("CARGO_BIN_EXE_usal");
/// Bound on one step over the radio (start-up of the whole mission included).
const STEP: Duration = Duration::from_secs(90);

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// Builds the services `usal run` starts into the directory holding `usal` (this test's
/// target directory): the one build every test that starts services asks for.
fn build_bins() {
    common::workspace_bin("vas");
}

/// The FMo as the test reaches it: its address and token.
struct Fmo {
    addr: String,
    token: String,
}

impl Fmo {
    async fn get(&self, path: &str) -> Value {
        let (status, body) = request_with(
            &self.addr,
            "GET",
            path,
            None,
            &format!("X-Station-Token: {}\r\n", self.token),
        )
        .await;
        assert_eq!(status, 200, "GET {path}: {body}");
        serde_json::from_str(&body).unwrap_or_else(|e| panic!("GET {path}: {e}: {body}"))
    }

    async fn post(&self, path: &str, body: Value) -> (u16, Value) {
        let (status, text) = request_with(
            &self.addr,
            "POST",
            path,
            Some(&body.to_string()),
            &format!("X-Station-Token: {}\r\n", self.token),
        )
        .await;
        (status, serde_json::from_str(&text).unwrap_or(Value::Null))
    }

    /// Polls the snapshot until `pred` holds.
    async fn wait(&self, what: &str, mut pred: impl FnMut(&Value) -> bool) -> Value {
        let deadline = tokio::time::Instant::now() + STEP;
        let mut last = Value::Null;
        while tokio::time::Instant::now() < deadline {
            last = self.get("/api/state").await;
            if pred(&last) {
                return last;
            }
            tokio::time::sleep(Duration::from_millis(200)).await;
        }
        panic!("no {what} within {STEP:?}; last state: {last:#}");
    }
}

fn rover(s: &Value) -> &Value {
    vehicle(s, "rover1").expect("rover1 in the FMo")
}

fn position(s: &Value) -> (f64, f64, f64) {
    let p = &rover(s)["position"]["value"];
    (
        p["lat"].as_f64().unwrap(),
        p["lon"].as_f64().unwrap(),
        p["heading"].as_f64().unwrap(),
    )
}

/// Metres north and east from `a` to `b`.
fn ne(a: (f64, f64, f64), b: (f64, f64, f64)) -> (f64, f64) {
    let r = 6_371_000.0_f64;
    (
        (b.0 - a.0).to_radians() * r,
        (b.1 - a.1).to_radians() * r * a.0.to_radians().cos(),
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fmo_manual_control_drives_mavsim_over_the_radio() {
    build_bins();
    // The shipped radio mission without its <station>: nothing else commands the rover.
    let src = std::fs::read_to_string(root().join("config/missions/rover-radio.xml"))
        .expect("the radio mission");
    let mission: String = src
        .lines()
        .filter(|l| !l.trim_start().starts_with("<station"))
        .map(|l| format!("{l}\n"))
        .collect();
    assert!(mission.contains("<radio ") && mission.contains("<fmo"));
    let dir = tempfile::tempdir().expect("tempdir");
    let file = dir.path().join("rover-radio-manual.xml");
    std::fs::write(&file, mission).expect("write the mission");

    let mut run = Command::new(USAL)
        .arg("run")
        .arg(&file)
        .args(["--speedup", "2", "--log"])
        .arg(dir.path().join("flight.jsonl.gz"))
        .current_dir(root())
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .kill_on_drop(true)
        .spawn()
        .expect("usal run starts");
    let mut lines = BufReader::new(run.stderr.take().expect("piped")).lines();
    let mut before = String::new();
    let url = tokio::time::timeout(STEP, async {
        while let Ok(Some(l)) = lines.next_line().await {
            before.push_str(&l);
            before.push('\n');
            if let Some((_, url)) = l.split_once("[ground/fmo] FMO_URL=") {
                return url.trim().to_owned();
            }
        }
        panic!("usal run ended before the FMo printed its URL");
    })
    .await
    .expect("the FMo's URL in time");
    // Keep reading the merged log so the launcher never blocks on a full pipe.
    let log = std::sync::Arc::new(std::sync::Mutex::new(before));
    let keep = log.clone();
    let reader = tokio::spawn(async move {
        while let Ok(Some(l)) = lines.next_line().await {
            let mut k = keep.lock().unwrap();
            k.push_str(&l);
            k.push('\n');
        }
    });
    let (base, token) = url.split_once("/?token=").expect("a token in the URL");
    let fmo = Fmo {
        addr: base.trim_start_matches("http://").to_owned(),
        token: token.to_owned(),
    };

    // Telemetry over the radio: the parked rover and its transitions.
    fmo.wait("rover1 PARKING with its transitions, over the radio", |s| {
        vehicle(s, "rover1").is_some_and(|v| {
            v["flight_state"]["value"] == "PARKING"
                && v["allowed"]["current"] == true
                && v["position"].is_object()
        })
    })
    .await;
    let (status, body) = fmo
        .post("/api/change_state", json!({"to": "MANUAL_NAVIGATION"}))
        .await;
    assert_eq!(status, 202, "{body}");
    let id = body["id"].as_u64().expect("a command id");
    let s = fmo
        .wait("MANUAL_NAVIGATION confirmed over the radio", |s| {
            command(s, id).is_some_and(|c| c["status"] != "pending")
                && rover(s)["flight_state"]["value"] == "MANUAL_NAVIGATION"
        })
        .await;
    assert_eq!(command(&s, id).unwrap()["status"], "ok", "{s:#}");

    // Throttle forward as the page posts it (20 Hz), for several seconds of radio latency.
    let start = position(&s);
    let t = tokio::time::Instant::now();
    while t.elapsed() < Duration::from_secs(6) {
        fmo.post(
            "/api/manual",
            json!({"throttle": 0.6, "deadman": true, "source": "keyboard"}),
        )
        .await;
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let moved = fmo
        .wait("the rover moving forward, seen over the radio", |s| {
            let (n, e) = ne(start, position(s));
            let h = start.2.to_radians();
            n * h.cos() + e * h.sin() > 1.0
        })
        .await;
    let (n, e) = ne(start, position(&moved));
    assert!((n * n + e * e).sqrt() > 1.0, "{n:.2} N {e:.2} E");

    // The dead-man released: the rover stops.
    fmo.post("/api/manual", json!({"deadman": false})).await;
    fmo.wait("the rover stopped", |s| {
        rover(s)["position"]["value"]["speed"]
            .as_f64()
            .is_some_and(|v| v < 0.1)
    })
    .await;

    // The radio carried it: the ground had no other way to the air node.
    let merged = log.lock().unwrap().clone();
    assert!(
        merged.contains("[usal] radio: marea-radio joins ground"),
        "no radio in the log:\n{merged}"
    );
    // SIGTERM: the launcher stops every child before it exits.
    let pid = run.id().expect("usal run is running");
    let pid = i32::try_from(pid).expect("pid fits");
    assert_eq!(sigterm(pid), 0);
    let status = tokio::time::timeout(STEP, run.wait())
        .await
        .expect("usal run stops on SIGTERM")
        .expect("status");
    assert!(status.success(), "{status}");
    reader.abort();

    // The flight log holds the pilot's manual control and the state taken.
    let file = std::fs::File::open(dir.path().join("flight.jsonl.gz")).expect("the log");
    let text = std::io::read_to_string(flate2::read::GzDecoder::new(file)).expect("gzip");
    let records: Vec<Value> = text
        .lines()
        .map(|l| serde_json::from_str(l).expect("JSON"))
        .collect();
    assert!(
        records.iter().any(|r| r["kind"] == "command"
            && r["name"] == "gcs/fmo/manual_control"
            && r["value"]["sticks"]["throttle"]
                .as_f64()
                .is_some_and(|t| t > 0.5)),
        "no manual control in the log"
    );
    assert!(records.iter().any(|r| r["kind"] == "state"
        && r["name"] == "rover1/vas/state_changed"
        && r["value"]["to"] == "MANUAL_NAVIGATION"));
    assert!(records
        .iter()
        .any(|r| r["name"] == "rover1/link/radio/stats"));
    assert_eq!(records.last().unwrap()["kind"], "end");
}

/// SIGTERM to `pid`, through the `kill` command (the crate denies unsafe code).
fn sigterm(pid: i32) -> i32 {
    let ok = std::process::Command::new("kill")
        .args(["-TERM", &pid.to_string()])
        .status()
        .is_ok_and(|s| s.success());
    if ok {
        0
    } else {
        -1
    }
}
