//! `usal run` end to end, with real child processes: the rover demo mission flies its plan to
//! completion; a killed VAS is restarted and the plan still completes; SIGINT leaves no child
//! behind; `usal list/echo/call` see a running mission, sealed so that another user's do not;
//! a malformed mission file starts nothing.

use std::io::{BufRead, BufReader, Read, Write};
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use serde_json::Value;

mod common;
// The test venv's Python (made from tests/python/requirements.txt), as the MAVSDK suite finds it.
#[path = "../services/vas/tests/common/mavsdk.rs"]
mod python;

const USAL: &str = env!("CARGO_BIN_EXE_usal");
/// Bound on a whole flight of the demo plan (about 10 s at --speedup 20 on an idle machine).
const FLIGHT: Duration = Duration::from_secs(150);
/// Bound on one step (a service starting, a tool answering).
const STEP: Duration = Duration::from_secs(30);

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// Builds the services `usal run` starts into the directory holding `usal`, where it looks
/// for them.
fn build_services() {
    let target = Path::new(USAL)
        .parent()
        .and_then(Path::parent)
        .expect("usal inside <target>/<profile>");
    test_support::build_services(target);
}

/// A `usal --json run ...` child: its JSON lines on a channel, stderr kept for failure reports,
/// and every process it reported killed on drop so a failed test leaves nothing behind.
struct Launcher {
    child: Child,
    lines: mpsc::Receiver<Value>,
    seen: Vec<Value>,
    stderr: std::sync::Arc<std::sync::Mutex<String>>,
}

impl Launcher {
    fn start(args: &[&str]) -> Launcher {
        build_services();
        let mut child = Command::new(USAL)
            .arg("--json")
            .arg("run")
            .args(args)
            // The flight log has its own test (tests/flightlog.rs); these runs leave no log in
            // the checkout.
            .arg("--no-log")
            .current_dir(root())
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .expect("starting usal run");
        let (tx, rx) = mpsc::channel();
        let out = child.stdout.take().expect("piped");
        std::thread::spawn(move || {
            for line in BufReader::new(out).lines() {
                let Ok(line) = line else { break };
                if let Ok(v) = serde_json::from_str::<Value>(&line) {
                    if tx.send(v).is_err() {
                        break;
                    }
                }
            }
        });
        let stderr = std::sync::Arc::new(std::sync::Mutex::new(String::new()));
        let keep = stderr.clone();
        let mut err = child.stderr.take().expect("piped");
        std::thread::spawn(move || {
            let mut buf = [0u8; 4096];
            while let Ok(n) = err.read(&mut buf) {
                if n == 0 {
                    break;
                }
                keep.lock()
                    .unwrap()
                    .push_str(&String::from_utf8_lossy(&buf[..n]));
            }
        });
        Launcher {
            child,
            lines: rx,
            seen: Vec::new(),
            stderr,
        }
    }

    fn stderr_tail(&self) -> String {
        let s = self.stderr.lock().unwrap();
        let start = s.len().saturating_sub(6000);
        let start = (start..s.len())
            .find(|i| s.is_char_boundary(*i))
            .unwrap_or(s.len());
        s[start..].to_owned()
    }

    /// The next JSON line satisfying `pred`, within `timeout`.
    fn expect(&mut self, timeout: Duration, what: &str, pred: impl Fn(&Value) -> bool) -> Value {
        let deadline = Instant::now() + timeout;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(v) => {
                    self.seen.push(v.clone());
                    if pred(&v) {
                        return v;
                    }
                }
                Err(_) => panic!(
                    "no {what} within {timeout:?}\nlines: {:?}\nstderr: {}",
                    self.seen,
                    self.stderr_tail()
                ),
            }
        }
    }

    /// Reads the lines of the next `window` and fails on one matching `pred`: `what` must
    /// not happen in it.
    fn none_within(&mut self, window: Duration, what: &str, pred: impl Fn(&Value) -> bool) {
        let deadline = Instant::now() + window;
        loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(v) => {
                    let hit = pred(&v);
                    self.seen.push(v.clone());
                    assert!(!hit, "{what} within {window:?}: {v}");
                }
                Err(mpsc::RecvTimeoutError::Timeout) => return,
                Err(mpsc::RecvTimeoutError::Disconnected) => {
                    panic!("usal ended within {window:?}: {}", self.stderr_tail())
                }
            }
        }
    }

    fn event(&mut self, timeout: Duration, name: &str) -> Value {
        self.expect(timeout, name, |v| v["event"] == name)
    }

    /// The mission's domain, as the launcher prints it first.
    /// Waits for the run's summary and a successful exit (status 0), then reads what is
    /// left of its output; returns the summary's event.
    fn completed(&mut self) -> Value {
        let summary = self.event(FLIGHT, "summary");
        let status = self.wait_exit(STEP);
        self.drain();
        assert!(status.success(), "{status}\n{}", self.stderr_tail());
        summary
    }

    fn domain(&mut self) -> String {
        self.event(STEP, "mission")["domain"]
            .as_str()
            .expect("the domain")
            .to_owned()
    }

    fn wait_exit(&mut self, timeout: Duration) -> std::process::ExitStatus {
        let deadline = Instant::now() + timeout;
        loop {
            if let Ok(Some(s)) = self.child.try_wait() {
                return s;
            }
            assert!(
                Instant::now() < deadline,
                "usal run did not exit within {timeout:?}\nstderr: {}",
                self.stderr_tail()
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Every line left after exit.
    fn drain(&mut self) {
        while let Ok(v) = self.lines.recv_timeout(Duration::from_secs(5)) {
            self.seen.push(v);
        }
    }

    /// Pids the launcher reported starting, with their service labels.
    fn pids(&self) -> Vec<(String, u32)> {
        self.seen
            .iter()
            .filter(|v| v["event"] == "started")
            .map(|v| {
                (
                    v["service"].as_str().unwrap_or_default().to_owned(),
                    v["pid"].as_u64().unwrap_or(0) as u32,
                )
            })
            .collect()
    }

    fn signal(&self, sig: &str) {
        signal(self.child.id(), sig);
    }
}

impl Drop for Launcher {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        // Every child it reported, the ones in lines a failed test never read too (its
        // children also get SIGTERM from the kernel when it dies).
        while let Ok(v) = self.lines.recv_timeout(Duration::from_millis(200)) {
            self.seen.push(v);
        }
        for (_, pid) in self.pids() {
            if alive(pid) {
                signal(pid, "KILL");
            }
        }
    }
}

fn signal(pid: u32, sig: &str) {
    let _ = Command::new("kill")
        .args([format!("-{sig}"), pid.to_string()])
        .status();
}

/// Whether `pid` is a live process (a zombie counts as gone: it has exited).
fn alive(pid: u32) -> bool {
    match std::fs::read_to_string(format!("/proc/{pid}/stat")) {
        Ok(stat) => stat
            .rsplit_once(") ")
            .is_some_and(|(_, rest)| !rest.starts_with('Z')),
        Err(_) => false,
    }
}

/// `fpma expand` of the demo plan: (leg, lat, lon) per waypoint.
fn nominal(plan: &Path) -> Vec<(String, f64, f64)> {
    let fpma = Path::new(USAL).with_file_name("fpma");
    let out = Command::new(fpma)
        // Expanded for the vehicle the plan names, as the launcher does.
        .args(["expand", plan.to_str().unwrap()])
        .output()
        .expect("fpma expand");
    assert!(out.status.success(), "{out:?}");
    String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| {
            let v: Value = serde_json::from_str(l).unwrap();
            (
                v["leg"].as_str().unwrap().to_owned(),
                v["lat"].as_f64().unwrap(),
                v["lon"].as_f64().unwrap(),
            )
        })
        .collect()
}

/// The summary's reached waypoints are the demo plan's, in order.
fn check_summary(summary: &Value) {
    check_summary_of(summary, "config/flightplans/rover-demo.xml", 300.0);
}

/// The summary's reached waypoints are those of `plan`, in order, and it flew more than
/// `min_m` metres, as planned.
fn check_summary_of(summary: &Value, plan: &str, min_m: f64) {
    let plan = nominal(&root().join(plan));
    assert_eq!(summary["completed"], true, "{summary}");
    assert_eq!(summary["in_order"], true, "{summary}");
    let reached = summary["reached"].as_array().expect("reached");
    assert_eq!(reached.len(), plan.len(), "{summary}");
    assert_eq!(summary["planned"], plan.len());
    let mut last_seq = None;
    for (r, (leg, lat, lon)) in reached.iter().zip(&plan) {
        assert_eq!(r["leg"].as_str(), Some(leg.as_str()), "{summary}");
        let seq = r["seq"].as_u64().unwrap();
        assert!(last_seq.is_none_or(|l| seq > l), "seqs increase: {summary}");
        last_seq = Some(seq);
        let (rlat, rlon) = (r["lat"].as_f64().unwrap(), r["lon"].as_f64().unwrap());
        assert!(
            (rlat - lat).abs() < 1e-6 && (rlon - lon).abs() < 1e-6,
            "{r} vs {lat},{lon}"
        );
    }
    let flown = summary["flown_m"].as_f64().unwrap();
    let planned = summary["planned_m"].as_f64().unwrap();
    assert!(flown > min_m && (flown - planned).abs() < 1.0, "{summary}");
}

fn assert_no_child_left(pids: &[(String, u32)]) {
    assert!(pids.len() >= 3, "mavsim, vas and fpma reported: {pids:?}");
    let left: Vec<_> = pids.iter().filter(|(_, p)| alive(*p)).collect();
    assert!(left.is_empty(), "still running: {left:?}");
}

#[test]
fn the_rover_demo_completes_and_its_summary_matches_the_plan() {
    let mut l = Launcher::start(&[
        "config/missions/rover-demo.xml",
        "--until-complete",
        "--speedup",
        "20",
    ]);
    let summary = l.completed();
    check_summary(&summary["summary"]);
    // Progress was shown waypoint by waypoint.
    let n: Vec<u64> = l
        .seen
        .iter()
        .filter(|v| v["event"] == "waypoint")
        .filter_map(|v| v["n"].as_u64())
        .collect();
    assert_eq!(n, (1..=n.len() as u64).collect::<Vec<_>>());
    assert_eq!(
        n.len(),
        summary["summary"]["planned"].as_u64().unwrap() as usize
    );
    // With an ETA from the speeds flown, shrinking as the plan goes on.
    let etas: Vec<f64> = l
        .seen
        .iter()
        .filter(|v| v["event"] == "waypoint")
        .filter_map(|v| v["eta_s"].as_f64())
        .collect();
    assert!(etas.len() >= 2, "no ETA shown: {etas:?}");
    assert!(etas.iter().all(|e| *e >= 0.0), "{etas:?}");
    assert!(etas[0] > *etas.last().unwrap(), "{etas:?}");
    let pids = l.pids();
    assert_no_child_left(&pids);
    // The merged log carries each child's prefix.
    let err = l.stderr_tail();
    assert!(
        err.contains("[air/vas] ") && err.contains("[air/fpma] "),
        "{err}"
    );
    // The stations' URLs carry their token; the VAS knows the mission's FMo.
    let all = l.stderr.lock().unwrap().clone();
    for line in [
        "[ground/fmo] FMO_URL=http://127.0.0.1:",
        "[ground/fpmo] FPMO_URL=http://127.0.0.1:",
    ] {
        let url = all
            .lines()
            .find(|l| l.contains(line))
            .unwrap_or_else(|| panic!("no {line} in the merged log"));
        let token = url.split_once("/?token=").map(|(_, t)| t.trim());
        assert!(token.is_some_and(|t| t.len() == 32), "{url}");
    }
    assert!(
        !all.contains("manualStations not set"),
        "the demo VAS obeys any station"
    );
}

/// A service of the user's own (examples/hello-service, `<service>` in the mission) runs beside
/// the VAS: its items are in `usal list` under its node, its function answers `usal call`, its
/// variable (computed from the VAS's position) shows in the FMo, and the mission completes.
#[test]
fn a_service_of_your_own_runs_beside_the_vas_and_shows_in_usal_list_and_the_fmo() {
    let mut l = Launcher::start(&[
        "config/missions/rover-hello.xml",
        "--until-complete",
        "--speedup",
        "5",
    ]);
    let domain = l.domain();
    l.expect(STEP, "the user's service started", |v| {
        v["event"] == "started" && v["service"] == "air/hello"
    });
    let deadline = Instant::now() + STEP;
    let listed = loop {
        let (ok, out) = tool(&domain, &["list"]);
        if ok && out.contains("rover1/hello/distance_m") {
            break out;
        }
        assert!(
            Instant::now() < deadline,
            "hello's items never listed: {out}"
        );
        std::thread::sleep(Duration::from_millis(200));
    };
    // Every item of the mission's services (VAS, FPMa, stations, links, the user's) is of a
    // type the tools decode: none is listed as raw.
    assert!(
        !listed.contains("(raw:"),
        "items usal cannot decode: {}",
        listed
            .lines()
            .filter(|l| l.contains("(raw:"))
            .collect::<Vec<_>>()
            .join("\n")
    );
    let node = listed
        .split("node ")
        .find(|n| n.starts_with("air-hello "))
        .unwrap_or_else(|| panic!("no node air-hello: {listed}"));
    for item in [
        "variable rover1/hello/distance_m",
        "variable rover1/hello/uptime_s",
        "event    rover1/hello/greeted",
        "function rover1/hello/greet",
        "subscribes    variable rover1/vas/position",
    ] {
        assert!(node.contains(item), "{item} missing: {node}");
    }
    let (ok, said) = tool(&domain, &["call", "rover1/hello/greet", r#""pilot""#]);
    assert!(ok && said.contains("hello, pilot"), "{said}");
    let (ok, said) = tool(&domain, &["call", "rover1/hello/greet", r#""""#]);
    assert!(
        !ok && said.contains("greet whom?"),
        "the service's own refusal: {said}"
    );
    let url = l
        .stderr
        .lock()
        .unwrap()
        .lines()
        .find_map(|line| {
            line.split_once("[ground/fmo] FMO_URL=")
                .map(|(_, u)| u.trim().to_owned())
        })
        .expect("the FMo's URL in the merged log");
    // The rover moves off: the distance the service computes grows, and the FMo shows it.
    let deadline = Instant::now() + Duration::from_secs(60);
    loop {
        let state = fmo_state(&url);
        let distance = state["vehicles"]
            .as_array()
            .and_then(|vs| vs.iter().find(|v| v["id"] == "rover1/vas"))
            .and_then(|v| v["services"].as_array())
            .and_then(|items| {
                items
                    .iter()
                    .find(|i| i["name"] == "rover1/hello/distance_m")
            })
            .and_then(|i| i["value"].as_f64());
        if distance.is_some_and(|d| d > 5.0) {
            // The pilot's instruments: the battery with its charge, and the plan's ETA.
            let v = state["vehicles"]
                .as_array()
                .and_then(|vs| vs.iter().find(|v| v["id"] == "rover1/vas"))
                .expect("rover1");
            assert!(
                v["battery"]["value"]["remaining"]
                    .as_f64()
                    .is_some_and(|r| r > 0.0),
                "{v}"
            );
            assert_eq!(v["plan"]["value"]["name"], "rover-demo", "{v}");
            break;
        }
        assert!(
            Instant::now() < deadline,
            "hello's distance never shown in the FMo: {state}"
        );
        std::thread::sleep(Duration::from_millis(300));
    }
    let summary = l.completed();
    check_summary(&summary["summary"]);
    let pids = l.pids();
    assert!(pids.iter().any(|(s, _)| s == "air/hello"), "{pids:?}");
    assert_no_child_left(&pids);
}

/// A user's service that keeps failing is restarted with backoff, then given up on, and the
/// mission flies on and completes: it is not one the flight needs.
#[test]
fn a_service_of_your_own_that_keeps_failing_does_not_stop_the_mission() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mission = demo_mission_with(
        dir.path(),
        "flaky.xml",
        &[(
            r#"<fpma vehicle="rover" lookahead="8"/>"#,
            r#"<fpma vehicle="rover" lookahead="8"/><service name="flaky" command="false"/>"#,
        )],
    );
    let mut l = Launcher::start(&[
        mission.to_str().expect("a UTF-8 path"),
        "--until-complete",
        "--speedup",
        "5",
    ]);
    let gave_up = l.expect(Duration::from_secs(60), "giving up on flaky", |v| {
        v["event"] == "gave_up" && v["service"] == "air/flaky"
    });
    assert!(
        gave_up["reason"]
            .as_str()
            .is_some_and(|r| r.contains("exited with status 1")),
        "{gave_up}"
    );
    let summary = l.completed();
    check_summary(&summary["summary"]);
    assert_no_child_left(&l.pids());
}

/// An autopilot the mission does not start (SITL, a flight controller on a serial port) is
/// named by `<autopilot endpoint family>` instead of a `<mavsim>`: the node's VAS flies it.
/// Here a mavsim started apart, on its own UDP port, in ArduPilot's and then in PX4's mode
/// encoding; the mission completes in both.
#[test]
fn a_mission_flies_an_autopilot_it_did_not_start_in_both_mode_encodings() {
    build_services();
    for family in ["ardupilot", "px4"] {
        let sim_bin = Path::new(USAL).with_file_name("mavsim");
        let mut sim = KilledOnDrop(
            Command::new(&sim_bin)
                .args(["--udp", "127.0.0.1:0", "--speedup", "20"])
                .args(["--home", "41.27500,1.98700,0", "--autopilot", family])
                .stdin(Stdio::piped())
                .stdout(Stdio::piped())
                .stderr(Stdio::null())
                .spawn()
                .expect("mavsim starts"),
        );
        let mut first = String::new();
        BufReader::new(sim.0.stdout.take().expect("piped"))
            .read_line(&mut first)
            .expect("mavsim says where it listens");
        let addr = first
            .trim()
            .strip_prefix("MAVSIM_UDP=")
            .unwrap_or_else(|| panic!("mavsim said {first:?}"))
            .to_owned();
        let dir = tempfile::tempdir().expect("tempdir");
        let mission = demo_mission_with(
            dir.path(),
            "external.xml",
            &[
                (
                    r#"<mavsim vehicle="rover" home="41.27500,1.98700,0" speedup="5"/>"#,
                    &format!(r#"<autopilot endpoint="udpout:{addr}" family="{family}"/>"#),
                ),
                (
                    r#"<fence maxDistance="300" action="hold">"#,
                    r#"<fence maxDistance="300" homeLat="41.275" homeLon="1.987" action="hold">"#,
                ),
            ],
        );
        let pids = completes_with_autopilot(&mission, sim, family);
        // The launcher started no simulator: only the VAS, the FPMa and the stations.
        assert!(
            pids.iter().all(|(s, _)| !s.ends_with("/mavsim")),
            "{family}: {pids:?}"
        );
        assert_no_child_left(&pids);
    }
}

/// The same against a vehicle built from MAVSDK's server plugins (a MAVLink implementation not
/// written here, speaking PX4's mode encoding, keeping no fence): named by `<autopilot
/// endpoint family="px4">`, flown through the rolling queue to the end of the plan.
#[test]
fn a_mission_flies_a_mavsdk_vehicle_it_did_not_start() {
    let Some(py) = python::python() else {
        return;
    };
    build_services();
    let port = python::free_udp_port();
    let mut vehicle = KilledOnDrop(
        Command::new(&py)
            .arg(root().join("tests/python/mavsdk_vehicle.py"))
            .args(["--port", &port.to_string(), "--speedup", "2"])
            .args(["--home", "41.27500,1.98700"])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::null())
            .spawn()
            .expect("the MAVSDK vehicle starts"),
    );
    let mut out = BufReader::new(vehicle.0.stdout.take().expect("piped"));
    let mut first = String::new();
    out.read_line(&mut first)
        .expect("the MAVSDK vehicle says it is ready");
    assert!(
        first.contains(r#""ready""#),
        "the MAVSDK vehicle said {first:?}"
    );
    // It prints a line per event for as long as it runs: read them (a closed pipe stops it).
    std::thread::spawn(move || out.lines().map_while(Result::ok).for_each(drop));
    let dir = tempfile::tempdir().expect("tempdir");
    // MAVSDK's servers keep no fence, and a vehicle whose autopilot does not take its fence
    // never starts (tested above): this mission has none.
    let demo = std::fs::read_to_string(root().join("config/missions/rover-demo.xml"))
        .expect("the demo mission");
    let fence = &demo[demo.find("<fence ").expect("the demo's fence")
        ..demo.find("</fence>").expect("its end") + "</fence>".len()];
    let mission = demo_mission_with(
        dir.path(),
        "mavsdk.xml",
        &[
            (
                r#"<mavsim vehicle="rover" home="41.27500,1.98700,0" speedup="5"/>"#,
                &format!(r#"<autopilot endpoint="udpout:127.0.0.1:{port}"/>"#),
            ),
            (fence, ""),
        ],
    );
    let pids = completes_with_autopilot(&mission, vehicle, "MAVSDK");
    assert_no_child_left(&pids);
}

/// Runs `mission` (which names `autopilot` by its endpoint) until complete: it exits 0 with a
/// summary that matches the plan. The autopilot is stopped once the launcher is; returns the
/// launcher's children.
fn completes_with_autopilot(
    mission: &Path,
    autopilot: KilledOnDrop,
    what: &str,
) -> Vec<(String, u32)> {
    let mut l = Launcher::start(&[mission.to_str().expect("UTF-8"), "--until-complete"]);
    let summary = l.event(FLIGHT, "summary");
    let status = l.wait_exit(STEP);
    l.drain();
    drop(autopilot);
    assert!(status.success(), "{what}: {status}\n{}", l.stderr_tail());
    check_summary(&summary["summary"]);
    l.pids()
}

/// A child the test started itself, killed when the test ends, a failed one included.
struct KilledOnDrop(Child);

impl Drop for KilledOnDrop {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A copter flies the survey as a pilot would: take off (the launcher asks for TAKE_OFF, then
/// for WAYPOINT_NAVIGATION once it has climbed), scan at 30 m, land on the pad, and is parked
/// and disarmed at the end; the summary compares altitudes and the touchdown with the plan.
#[test]
fn the_copter_demo_takes_off_surveys_at_altitude_and_lands_on_the_pad() {
    let a = fly_aircraft_mission(
        "config/missions/copter-demo.xml",
        "config/flightplans/copter-survey.xml",
        3_000.0,
    );
    assert_eq!(a["alt_ref"], "REL", "{a}");
    let landing = a["landing_error_m"].as_f64().expect("a touchdown");
    assert!(landing < 5.0, "touched down {landing} m from the pad: {a}");
    assert_eq!(a["planned_alt_m"], serde_json::json!([30.0, 30.0]), "{a}");
    assert!(a["waypoints_checked"].as_u64().unwrap() >= 18, "{a}");
    let highest = a["highest_m"].as_f64().unwrap();
    assert!((29.0..35.0).contains(&highest), "{a}");
}

/// A plane flies a circuit with altitude changes and a hold, then glides down the approach
/// onto the strip, parked and disarmed at the end. The landing is flown as ArduPilot flies
/// one: the autopilot passes a DO_LAND_START, then the approach fix, then lands.
#[test]
fn the_plane_demo_flies_its_circuit_and_lands_on_the_strip() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mission = dir.path().join("plane-demo.xml");
    let demo = std::fs::read_to_string(root().join("config/missions/plane-demo.xml"))
        .expect("the plane demo")
        .replace(
            "../flightplans/",
            &root().join("config/flightplans/").display().to_string(),
        )
        .replacen("<mavsim ", r#"<mavsim log="mavsim.jsonl" "#, 1);
    std::fs::write(&mission, demo).expect("write the mission");
    let a = fly_aircraft_mission(
        mission.to_str().expect("UTF-8"),
        "config/flightplans/plane-circuit.xml",
        9_000.0,
    );
    let log: Vec<Value> = std::fs::read_to_string(dir.path().join("mavsim.jsonl"))
        .expect("mavsim's log")
        .lines()
        .map(|l| serde_json::from_str(l).expect("a JSON line"))
        .collect();
    const DO_LAND_START: u64 = 189;
    let marker = log
        .iter()
        .position(|e| e["event"] == "do_command" && e["command"] == DO_LAND_START)
        .expect("the autopilot passed a DO_LAND_START");
    let after: Vec<&Value> = log[marker..]
        .iter()
        .filter(|e| e["event"] == "item_reached" || e["event"] == "landed")
        .collect();
    let faf = (41.275, 2.0014);
    assert!(
        (after[0]["lat"].as_f64().unwrap() - faf.0).abs() < 1e-6
            && (after[0]["lon"].as_f64().unwrap() - faf.1).abs() < 1e-6,
        "the approach fix follows the marker: {after:?}"
    );
    assert!(after.iter().any(|e| e["event"] == "landed"), "{after:?}");
    assert!(
        log[..marker].iter().all(|e| e["event"] != "item_reached"
            || (e["lat"].as_f64().unwrap() - faf.0).abs() > 1e-6
            || (e["lon"].as_f64().unwrap() - faf.1).abs() > 1e-6),
        "the marker precedes the approach"
    );
    assert_eq!(a["alt_ref"], "MSL", "{a}");
    let landing = a["landing_error_m"].as_f64().expect("a touchdown");
    assert!(
        landing < 150.0,
        "came to rest {landing} m from the touchdown point: {a}"
    );
    assert_eq!(a["planned_alt_m"], serde_json::json!([80.0, 180.0]), "{a}");
    let highest = a["highest_m"].as_f64().unwrap();
    assert!((175.0..200.0).contains(&highest), "{a}");
}

/// Runs an aircraft mission to completion and checks what every aircraft flight must show:
/// the plan's waypoints in order, take-off asked before navigation (and navigation only after
/// the climb), nothing asked out of order, parked on the ground at the end, and altitudes
/// flown as planned. Returns the summary's aircraft part.
fn fly_aircraft_mission(mission: &str, plan: &str, min_m: f64) -> Value {
    let mut l = Launcher::start(&[mission, "--until-complete", "--speedup", "20"]);
    let summary = l.completed();
    let summary = &summary["summary"];
    check_summary_of(summary, plan, min_m);
    let kicks: Vec<&str> = l
        .seen
        .iter()
        .filter_map(|v| v["event"].as_str())
        .filter(|e| e.ends_with("_kicked"))
        .collect();
    assert_eq!(kicks, ["takeoff_kicked", "navigation_kicked"], "{summary}");
    let state_at = |name: &str| {
        l.seen
            .iter()
            .position(|v| v["event"] == "state" && v["state"] == name)
    };
    let (took_off, navigated) = (state_at("TAKE_OFF"), state_at("WAYPOINT_NAVIGATION"));
    assert!(took_off.is_some() && took_off < navigated, "{summary}");
    assert!(
        l.seen.iter().all(|v| v["event"] != "navigation_refused"),
        "nothing asked out of order"
    );
    let last_state = l
        .seen
        .iter()
        .rev()
        .find(|v| v["event"] == "state")
        .map(|v| v["state"].clone());
    assert_eq!(last_state, Some(Value::from("PARKING")), "{summary}");
    let a = summary["aircraft"].clone();
    assert_eq!(a["took_off"], true, "{a}");
    assert_eq!(a["landed"], true, "{a}");
    let worst = a["worst_alt_error_m"].as_f64().expect("altitudes compared");
    assert!(worst.abs() < 2.0, "{a}");
    assert_no_child_left(&l.pids());
    a
}

/// The same mission with the ground on the far side of an emulated 57600-baud radio with byte
/// errors: gateways on both sides carry the plan upload, the commands and the telemetry.
#[test]
fn the_rover_radio_mission_completes_over_a_lossy_radio() {
    let mut l = Launcher::start(&[
        "config/missions/rover-radio.xml",
        "--until-complete",
        "--speedup",
        "20",
    ]);
    let radio = l.event(STEP, "radio");
    assert!(
        radio["ground"]
            .as_str()
            .is_some_and(|p| p.starts_with("/dev/")),
        "{radio}"
    );
    let summary = l.event(FLIGHT * 2, "summary");
    let status = l.wait_exit(STEP);
    l.drain();
    assert!(status.success(), "{status}\n{}", l.stderr_tail());
    check_summary(&summary["summary"]);
    let pids = l.pids();
    // A gateway ran on each side of the radio.
    for gw in ["air/gateway", "ground/gateway"] {
        assert!(
            pids.iter().any(|(s, _)| s == gw),
            "{gw} not started: {pids:?}"
        );
    }
    assert_no_child_left(&pids);
    // Quiet by default: the gateways' output is relayed (their ready line), their tables of
    // what they forward are not (`--verbose` shows them).
    let err = l.stderr.lock().unwrap().clone();
    assert!(err.contains("\"ready\":\"air-gateway\""), "{err}");
    assert!(
        !err.contains("\"forwarded\":"),
        "a gateway table was printed"
    );
}

/// The same mission with air and ground on LANs of their own, no multicast between them, each
/// reaching one Zenoh router (`usal-router`, over TLS with certificates made for the run)
/// through a gateway with a `<zenoh>` link: the plan upload, the commands and the telemetry all
/// cross the router. A plain Zenoh client (the official Python one, with the run's client
/// configuration) reads the VAS's position as JSON from the router's bridge meanwhile.
#[test]
fn the_rover_wan_mission_completes_through_a_zenoh_router() {
    let Some(py) = python::python() else {
        return;
    };
    let mut l = Launcher::start(&[
        "config/missions/rover-wan.xml",
        "--until-complete",
        "--speedup",
        "20",
    ]);
    let router = l.event(STEP, "router");
    assert!(
        router["endpoint"]
            .as_str()
            .is_some_and(|e| e.starts_with("tls/127.0.0.1:") && !e.ends_with(":0")),
        "{router}"
    );
    // The run's certificates, and the configuration a Zenoh client needs to trust them.
    let client = router["client_config"]
        .as_str()
        .expect("TLS client configuration");
    assert!(std::fs::read_to_string(client).is_ok_and(|c| c.contains("root_ca_certificate")));
    let domain = l
        .seen
        .iter()
        .find(|v| v["event"] == "mission")
        .and_then(|v| v["domain"].as_str())
        .expect("the mission's domain")
        .to_owned();
    // The mission's nodes behind their gateways too (those that offer something).
    const NODES: [&str; 4] = ["air", "air-gateway", "bridge", "ground-gateway"];
    let mut watcher = common::Proc::spawn(
        "python",
        py.to_str().expect("a UTF-8 path"),
        &[
            python::repo_root()
                .join("tests/python/zenoh_watch.py")
                .display()
                .to_string(),
            router["endpoint"].as_str().unwrap_or_default().to_owned(),
            client.to_owned(),
            domain,
            "rover1/vas/position".into(),
        ]
        .into_iter()
        .chain(NODES.iter().map(|n| n.to_string()))
        .collect::<Vec<_>>(),
    );
    let position = watcher.expect_key(STEP, "sample");
    assert_eq!(position["encoding"], "application/json", "{position}");
    assert!(
        position["sample"]["lat"]
            .as_f64()
            .is_some_and(|lat| (lat - 41.275).abs() < 0.01),
        "{position}"
    );
    let nodes = watcher.expect_key(STEP, "nodes");
    for n in NODES {
        assert!(
            nodes["nodes"]
                .as_array()
                .is_some_and(|a| a.iter().any(|x| x == n)),
            "{n} missing from {nodes}"
        );
    }
    watcher.expect_key(STEP, "done");
    let summary = l.event(FLIGHT * 2, "summary");
    let status = l.wait_exit(STEP);
    l.drain();
    assert!(status.success(), "{status}\n{}", l.stderr_tail());
    check_summary(&summary["summary"]);
    let pids = l.pids();
    for p in ["router", "air/gateway", "ground/gateway"] {
        assert!(
            pids.iter().any(|(s, _)| s == p),
            "{p} not started: {pids:?}"
        );
    }
    assert_no_child_left(&pids);
}

/// The WAN rehearsal: the ground station behind 150 ms of round trip, 1 % segment loss and
/// 2 Mbit/s, the router killed and restarted mid-flight, then the ground's path cut for 30 s:
/// the VAS holds the rover on the lost link and resumes when it returns, nothing the vehicle
/// raised is lost to the station (every waypoint reached, in order; both failsafes seen), and
/// the plan completes. At 5x (the mission flies at 2x, for people to watch) the plan is still
/// being flown when the faults come: it needs ~45 s of flight, the outage starts at 20 s and
/// holds the rover for its 30 s.
#[test]
fn the_rover_wan_failsafe_mission_completes_across_a_router_restart_and_an_outage() {
    let mut l = Launcher::start(&[
        "config/missions/rover-wan-failsafe.xml",
        "--until-complete",
        "--speedup",
        "5",
    ]);
    let wan = l.event(STEP, "wan");
    assert_eq!(wan["rtt_ms"], 150, "{wan}");
    l.expect(Duration::from_secs(60), "the router killed", |v| {
        v["event"] == "crash" && v["service"] == "router"
    });
    l.expect(Duration::from_secs(30), "the router restarted", |v| {
        v["event"] == "started" && v["service"] == "router" && v["restarts"] == 1
    });
    let summary = l.event(FLIGHT * 3, "summary");
    let status = l.wait_exit(STEP);
    l.drain();
    assert!(status.success(), "{status}\n{}", l.stderr_tail());
    check_summary(&summary["summary"]);
    let fired: Vec<String> = summary["summary"]["failsafes"]
        .as_array()
        .map(|a| {
            a.iter()
                .map(|f| {
                    format!(
                        "{} {}",
                        f["kind"].as_str().unwrap_or(""),
                        f["action"].as_str().unwrap_or("")
                    )
                })
                .collect()
        })
        .unwrap_or_default();
    assert!(
        fired.contains(&"link-lost hold".to_owned())
            && fired.contains(&"link-restored resume".to_owned()),
        "{fired:?}"
    );
    assert_no_child_left(&l.pids());
}

/// Two rovers in one mission, each its namespace, simulator, VAS, FPMa and
/// plan; `--until-complete` waits for both, and each gets its own progress and summary.
#[test]
fn two_rovers_in_one_mission_each_complete_their_own_plan() {
    let mut l = Launcher::start(&[
        "config/missions/two-rovers.xml",
        "--until-complete",
        "--speedup",
        "20",
    ]);
    let fleet = l.event(FLIGHT * 2, "fleet_summary");
    let status = l.wait_exit(STEP);
    l.drain();
    assert!(status.success(), "{status}\n{}", l.stderr_tail());
    assert_eq!(fleet["vehicles"], 2, "{fleet}");
    assert_eq!(fleet["completed"], serde_json::json!(["rover1", "rover2"]));
    let summaries: Vec<&Value> = l
        .seen
        .iter()
        .filter(|v| v["event"] == "summary")
        .map(|v| &v["summary"])
        .collect();
    assert_eq!(summaries.len(), 2, "{summaries:?}");
    for (vehicle, plan, min_m) in [
        ("rover1", "config/flightplans/rover-demo.xml", 300.0),
        ("rover2", "config/flightplans/rover-east.xml", 200.0),
    ] {
        let s = summaries
            .iter()
            .find(|s| s["vehicle"] == vehicle)
            .unwrap_or_else(|| panic!("no summary of {vehicle}: {summaries:?}"));
        check_summary_of(s, plan, min_m);
        // Each vehicle's progress came waypoint by waypoint, named after it.
        let n: Vec<u64> = l
            .seen
            .iter()
            .filter(|v| v["event"] == "waypoint" && v["vehicle"] == vehicle)
            .filter_map(|v| v["n"].as_u64())
            .collect();
        assert_eq!(n, (1..=s["planned"].as_u64().unwrap()).collect::<Vec<_>>());
    }
    let pids = l.pids();
    for svc in [
        "air1/mavsim",
        "air1/vas",
        "air1/fpma",
        "air2/mavsim",
        "air2/vas",
        "air2/fpma",
    ] {
        assert!(
            pids.iter().any(|(s, _)| s == svc),
            "{svc} not started: {pids:?}"
        );
    }
    assert_no_child_left(&pids);
}

/// The points of interest the search missions place (`config/search/pois.txt`).
fn placed_pois() -> usize {
    let pois = std::fs::read_to_string(root().join("config/search/pois.txt")).unwrap();
    pois.lines()
        .filter(|l| !l.trim().is_empty() && !l.trim_start().starts_with('#'))
        .count()
}

/// The Broz search through real processes. The surveyor's mavsim detects
/// the mission's points of interest, the fleet service re-tasks the investigator to each, the
/// surveyor is paused and resumed by a call to the fleet service meanwhile, and the run ends 0
/// once the area is covered and every detection visited, with no separation violation.
#[test]
fn the_search_mission_visits_every_detection_with_no_separation_violation() {
    let placed = placed_pois();
    let mut l = Launcher::start(&[
        "config/missions/search.xml",
        "--until-complete",
        "--speedup",
        "10",
    ]);
    let domain = l.domain();
    // Once the surveyor has found something (it is then scanning), pause it and resume it.
    l.expect(FLIGHT, "a detection", |v| {
        v["event"] == "fleet_progress" && v["detections"].as_u64().is_some_and(|d| d >= 1)
    });
    let (ok, answer) = tool(&domain, &["call", "gcs/fleet/pause", r#""surveyor""#]);
    assert!(ok && answer.contains("surveyor paused"), "{answer}");
    // The status shows it paused and stopped (it is published within 250 ms of a change).
    let surveyor = |echo: &str| -> Value {
        let json = echo.find('{').map_or("null", |i| echo[i..].trim());
        let v: Value = serde_json::from_str(json).unwrap_or(Value::Null);
        v["vehicles"][0].clone()
    };
    let deadline = Instant::now() + STEP;
    loop {
        let (ok, echo) = tool(&domain, &["echo", "gcs/fleet/status", "--count", "1"]);
        assert!(ok, "{echo}");
        let v = surveyor(&echo);
        if v["paused"] == true && v["state"] == "PARKING" {
            assert_eq!(
                (&v["id"], v["priority"].as_i64()),
                (&Value::from("surveyor"), Some(2))
            );
            break;
        }
        assert!(
            Instant::now() < deadline,
            "the surveyor is not shown paused: {echo}"
        );
    }
    let (ok, answer) = tool(&domain, &["call", "gcs/fleet/resume", r#""surveyor""#]);
    assert!(ok && answer.contains("surveyor resumed"), "{answer}");
    let (ok, answer) = tool(&domain, &["call", "gcs/fleet/pause", r#""nobody""#]);
    assert!(!ok && answer.contains("no vehicle `nobody`"), "{answer}");

    let end = l.event(FLIGHT * 2, "fleet_plan_summary");
    let status = l.wait_exit(STEP);
    l.drain();
    assert!(status.success(), "{status}\n{}", l.stderr_tail());
    let s = &end["summary"];
    assert_eq!(s["done"], true, "{end}");
    let detections = s["detections"].as_array().unwrap();
    assert_eq!(detections.len(), placed, "every point found: {end}");
    // The shed between the investigator and the area: driven round, never entered.
    let sep = &s["separation"];
    assert_eq!(sep["obstacle_entries"], 0, "{end}");
    assert!(sep["detours"].as_u64().is_some_and(|d| d >= 1), "{end}");
    assert_eq!(s["obstacles"][0]["name"], "shed", "{end}");
    // Typed detections (the VAS's `detection` event): how sure the detector was, as it passed.
    assert!(
        detections.iter().all(|d| d["confidence"]
            .as_f64()
            .is_some_and(|c| (0.5..=1.0).contains(&c))),
        "{end}"
    );
    assert!(
        detections.iter().all(|d| d["visited"].is_array()),
        "every detection visited: {end}"
    );
    let mut order: Vec<u64> = s["visit_order"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(Value::as_u64)
        .collect();
    order.sort_unstable();
    assert_eq!(order, (1..=placed as u64).collect::<Vec<_>>(), "{end}");
    assert_eq!(end["visited_ratio"], 1.0);
    assert_eq!(s["separation"]["violations"], 0, "{end}");
    assert!(
        s["separation"]["closest_m"].as_f64().unwrap() >= 5.0,
        "{end}"
    );
    let pids = l.pids();
    for svc in ["air1/mavsim", "air2/mavsim", "ground/fleet"] {
        assert!(pids.iter().any(|(p, _)| p == svc), "{svc}: {pids:?}");
    }
    assert_no_child_left(&pids);
}

/// The two-drone search as Broz flew it: two copters take off, the surveyor scans at 30 m, the
/// investigator visits every detection at 10 m round the shed in its way, and both land back
/// on their pads; the summary says so, copter by copter.
#[test]
fn the_copter_search_takes_off_visits_every_detection_and_lands_both() {
    let placed = placed_pois();
    let mut l = Launcher::start(&[
        "config/missions/search-copters.xml",
        "--until-complete",
        "--speedup",
        "20",
    ]);
    let end = l.event(FLIGHT * 2, "fleet_plan_summary");
    let status = l.wait_exit(STEP);
    l.drain();
    assert!(status.success(), "{status}\n{}", l.stderr_tail());
    let s = &end["summary"];
    assert_eq!(s["done"], true, "{end}");
    let detections = s["detections"].as_array().unwrap();
    assert_eq!(detections.len(), placed, "every point found: {end}");
    assert!(
        detections
            .iter()
            .all(|d| d["visited"][0] == "investigator" && d["by"] == "surveyor"),
        "every detection the surveyor made visited by the investigator: {end}"
    );
    assert_eq!(end["visited_ratio"], 1.0);
    // The shed (6 m) is in the investigator's way at 10 m: flown round, never entered.
    let sep = &s["separation"];
    assert_eq!(sep["obstacle_entries"], 0, "{end}");
    assert!(sep["detours"].as_u64().is_some_and(|d| d >= 1), "{end}");
    // 20 m apart in altitude: never a conflict, whatever their horizontal distance.
    assert_eq!(
        (sep["violations"].as_u64(), sep["holds"].as_u64()),
        (Some(0), Some(0)),
        "{end}"
    );
    // Each copter took off to its altitude and landed on its pad, disarmed.
    for (k, (id, alt)) in [("surveyor", 30.0), ("investigator", 10.0)]
        .into_iter()
        .enumerate()
    {
        let v = &s["vehicles"][k];
        assert_eq!(v["id"], id, "{end}");
        let a = &v["aircraft"];
        assert_eq!(a["took_off"], true, "{id}: {end}");
        assert_eq!(a["takeoff_alt_m"].as_f64(), Some(alt), "{id}: {end}");
        assert!(
            a["highest_m"]
                .as_f64()
                .is_some_and(|h| h >= alt - 1.5 && h < alt + 5.0),
            "{id} flew at its altitude: {end}"
        );
        // En route (take-off and touchdown aside) it held the plans' altitude.
        assert!(
            a["waypoints_checked"].as_u64().is_some_and(|n| n >= 2)
                && a["worst_alt_error_m"]
                    .as_f64()
                    .is_some_and(|e| e.abs() < 2.0),
            "{id} held its altitude en route: {end}"
        );
        assert_eq!(a["landed"], true, "{id}: {end}");
        assert!(
            a["landing_error_m"].as_f64().is_some_and(|d| d < 5.0),
            "{id} on its pad: {end}"
        );
        assert_eq!(v["state"], "PARKING", "{id}: {end}");
    }
    // The summary in words (what a run without --json prints): take-offs, landings,
    // detections, the shed.
    let status: flightplan::fleet_api::FleetStatus =
        serde_json::from_value(s.clone()).expect("the summary is a fleet status");
    let text = status.text("search-copters");
    for want in [
        "take-off: to 30 m REL planned",
        "take-off: to 10 m REL planned",
        "landing: on the ground, disarmed",
        &format!("detections: {placed} reported, {placed} visited"),
        "obstacles: 1 (shed)",
        "entered 0 times",
    ] {
        assert!(text.contains(want), "no `{want}` in the summary:\n{text}");
    }
    let pids = l.pids();
    for svc in ["air1/mavsim", "air1/camera", "air2/mavsim", "ground/fleet"] {
        assert!(pids.iter().any(|(p, _)| p == svc), "{svc}: {pids:?}");
    }
    assert_no_child_left(&pids);
}

/// The same search over the radio arrangement (an air LAN per rover, one
/// ground LAN, a lossy marea-radio per rover): the fleet layer commands both rovers across.
#[test]
fn the_search_over_a_radio_per_rover_visits_every_detection() {
    let mut l = Launcher::start(&[
        "config/missions/search-radio.xml",
        "--until-complete",
        "--speedup",
        "5",
    ]);
    let end = l.event(FLIGHT * 3, "fleet_plan_summary");
    let status = l.wait_exit(STEP);
    l.drain();
    assert!(status.success(), "{status}\n{end}\n{}", l.stderr_tail());
    let s = &end["summary"];
    assert_eq!(s["done"], true, "{end}");
    assert_eq!(end["visited_ratio"], 1.0, "{end}");
    assert_eq!(s["detections"].as_array().unwrap().len(), 5, "{end}");
    assert_eq!(s["separation"]["violations"], 0, "{end}");
    let pids = l.pids();
    for svc in [
        "air1/gateway",
        "air2/gateway",
        "ground/gateway",
        "ground/gateway-air2",
    ] {
        assert!(pids.iter().any(|(p, _)| p == svc), "{svc}: {pids:?}");
    }
    assert_no_child_left(&pids);
}

#[test]
fn a_killed_vas_is_restarted_and_the_plan_still_completes() {
    let mut l = Launcher::start(&[
        "config/missions/rover-demo.xml",
        "--until-complete",
        "--speedup",
        "10",
    ]);
    let vas = l.expect(STEP, "vas started", |v| {
        v["event"] == "started" && v["service"] == "air/vas"
    });
    let pid = vas["pid"].as_u64().unwrap() as u32;
    // In the middle of the scan.
    l.expect(FLIGHT, "waypoint 5", |v| {
        v["event"] == "waypoint" && v["n"].as_u64() >= Some(5)
    });
    signal(pid, "KILL");
    let again = l.expect(STEP, "vas restarted", |v| {
        v["event"] == "started" && v["service"] == "air/vas"
    });
    assert_ne!(again["pid"].as_u64(), Some(u64::from(pid)));
    assert_eq!(again["restarts"], 1);
    l.event(STEP, "vas_recovered");
    let summary = l.completed();
    assert_eq!(summary["summary"]["vas_recoveries"], 1);
    // Each waypoint reported once, in order, the plan's legs; positions are those of the plan.
    check_summary(&summary["summary"]);
    assert_no_child_left(&l.pids());
}

/// The pilot's Start: `usal call rover1/vas/change_state` to WAYPOINT_NAVIGATION, answered.
fn press_start_as_the_pilot(domain: &str) {
    let (ok, answer) = tool(
        domain,
        &[
            "call",
            "rover1/vas/change_state",
            r#"{"to":"WAYPOINT_NAVIGATION"}"#,
        ],
    );
    assert!(ok, "{answer}");
}

fn tool(domain: &str, args: &[&str]) -> (bool, String) {
    tool_with_state(None, domain, args)
}

/// [`tool`] run as another user would: with `state` as its state directory (where a mission's
/// domain key would be), not ours.
fn tool_with_state(state: Option<&Path>, domain: &str, args: &[&str]) -> (bool, String) {
    let mut command = Command::new(USAL);
    if let Some(dir) = state {
        command.env("XDG_STATE_HOME", dir);
    }
    let mut child = command
        .args(["--domain", domain])
        .args(args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("usal tool");
    let deadline = Instant::now() + STEP;
    loop {
        if let Ok(Some(_)) = child.try_wait() {
            break;
        }
        if Instant::now() >= deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("usal {args:?} did not finish within {STEP:?}");
        }
        std::thread::sleep(Duration::from_millis(50));
    }
    let out = child.wait_with_output().expect("tool output");
    (
        out.status.success(),
        format!(
            "{}{}",
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        ),
    )
}

/// The demo mission written in `dir` as `name`, its plans found where they are and each
/// `(from, to)` of `changes` made (each must apply: the demo's text changed otherwise).
fn demo_mission_with(dir: &Path, name: &str, changes: &[(&str, &str)]) -> std::path::PathBuf {
    let mission = dir.join(name);
    let flightplans = root().join("config/flightplans/");
    let mut demo = std::fs::read_to_string(root().join("config/missions/rover-demo.xml"))
        .expect("the demo mission")
        .replace("../flightplans/", &flightplans.display().to_string());
    for (from, to) in changes {
        assert!(demo.contains(from), "the demo mission has no {from}");
        demo = demo.replace(from, to);
    }
    std::fs::write(&mission, demo).expect("write the mission");
    mission
}

/// The demo mission with `<station start="operator">`, written in `dir`.
fn operator_mission(dir: &Path) -> std::path::PathBuf {
    demo_mission_with(
        dir,
        "rover-operator.xml",
        &[(r#"start="auto""#, r#"start="operator""#)],
    )
}

/// Another ground station writes the autopilot's mission mid-flight (a pymavlink station
/// behind the VAS's `<forward>`): the FPMa stops feeding the VAS and pauses the plan, `usal
/// run` says who took over and records it, the FPMa's progress carries it for the stations,
/// nothing resumes the plan by itself, and the operator's `resume` takes the vehicle back.
#[test]
fn a_mission_written_by_another_station_pauses_the_plan_until_the_operator_resumes_it() {
    let Some(py) = python::python() else {
        return;
    };
    let dir = tempfile::tempdir().expect("tempdir");
    let port = python::free_udp_port();
    std::fs::write(
        dir.path().join("vas.xml"),
        format!(r#"<vas><forward endpoint="udpout:127.0.0.1:{port}"/></vas>"#),
    )
    .expect("write the VAS config");
    let mission = demo_mission_with(
        dir.path(),
        "rover-takeover.xml",
        &[(
            r#"<vas vehicle="rover" queueSize="5" telemetryHz="4">"#,
            r#"<vas vehicle="rover" queueSize="5" telemetryHz="4" config="vas.xml">"#,
        )],
    );
    let mut gcs = Command::new(&py)
        .arg(root().join("tests/python/second_gcs.py"))
        .args(["--port", &port.to_string()])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("starting second_gcs.py");
    let mut gcs_in = gcs.stdin.take().expect("stdin");
    let (gcs_tx, gcs_lines) = mpsc::channel::<Value>();
    let gcs_out = gcs.stdout.take().expect("stdout");
    std::thread::spawn(move || {
        for line in BufReader::new(gcs_out).lines().map_while(Result::ok) {
            if let Ok(v) = serde_json::from_str::<Value>(&line) {
                if gcs_tx.send(v).is_err() {
                    break;
                }
            }
        }
    });
    let gcs_event = |what: &str| {
        let v = gcs_lines
            .recv_timeout(STEP)
            .unwrap_or_else(|_| panic!("the second station said no {what}"));
        assert_eq!(v["event"], what, "{v}");
        v
    };

    let mut l = Launcher::start(&[mission.to_str().expect("a UTF-8 path"), "--speedup", "5"]);
    let domain = l.domain();
    l.expect(STEP, "WAYPOINT_NAVIGATION", |v| {
        v["event"] == "state" && v["state"] == "WAYPOINT_NAVIGATION"
    });
    l.event(STEP, "waypoint");
    gcs_event("heartbeat");
    writeln!(
        gcs_in,
        "upload 41.2750,1.9870;41.2752,1.9872;41.2754,1.9870;41.2756,1.9872"
    )
    .expect("asking the second station to upload");
    let up = gcs_event("uploaded");
    assert_eq!(
        up["result"], 0,
        "the autopilot took the other mission: {up}"
    );

    let taken = l.event(STEP, "taken_over");
    assert!(
        taken["by"]
            .as_str()
            .is_some_and(|b| b.contains("system 250")),
        "{taken}"
    );
    assert_eq!(taken["items"], 4, "{taken}");
    let progress = |l: &Launcher| {
        let (ok, out) = tool(&domain, &["echo", "rover1/fpma/progress", "--count", "1"]);
        assert!(ok, "{out}\n{}", l.stderr_tail());
        out
    };
    let p = progress(&l);
    assert!(
        p.contains("\"taken_over\":\"MAVLink system 250") && p.contains("4 items"),
        "{p}"
    );
    // Nobody but the operator takes the vehicle back: no plan progress, no Start.
    l.none_within(
        Duration::from_secs(3),
        "the plan going on after the takeover",
        |v| v["event"] == "waypoint" || v["event"] == "navigation_kicked",
    );

    // Following the progress as the operator resumes: a sample without the takeover follows.
    let mut echo = Command::new(USAL)
        .args(["--domain", &domain, "echo", "rover1/fpma/progress"])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::null())
        .spawn()
        .expect("usal echo");
    let (tx, samples) = mpsc::channel::<String>();
    let out = echo.stdout.take().expect("piped stdout");
    std::thread::spawn(move || {
        for line in BufReader::new(out).lines().map_while(Result::ok) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    let first = samples.recv_timeout(STEP).expect("the progress as it is");
    assert!(first.contains("\"taken_over\":\""), "{first}");
    let (ok, answer) = tool(&domain, &["call", "rover1/fpma/resume"]);
    assert!(ok, "resume: {answer}");
    let deadline = Instant::now() + STEP;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let sample = samples
            .recv_timeout(left)
            .expect("the takeover outlived the operator's resume");
        if !sample.contains("\"taken_over\":\"") {
            break;
        }
    }
    let _ = echo.kill();
    let _ = echo.wait();
    drop(gcs_in);
    let _ = gcs.kill();
    let _ = gcs.wait();
    l.signal("INT");
    let status = l.wait_exit(STEP);
    l.drain();
    assert!(status.success(), "{status}");
}

/// The launcher's scratch directory (generated network files and the like) is private to the
/// user and named unpredictably, so nobody else can read it or make it first; it is gone
/// once the run ends.
#[test]
fn the_scratch_directory_is_private_unpredictable_and_removed_at_the_end() {
    use std::os::unix::fs::PermissionsExt;
    let mut l = Launcher::start(&["config/missions/rover-demo.xml", "--speedup", "5"]);
    let mission = l.event(STEP, "mission");
    let domain = mission["domain"].as_str().expect("the domain");
    let scratch = std::path::PathBuf::from(mission["scratch"].as_str().expect("the scratch path"));
    let name = scratch
        .file_name()
        .and_then(|n| n.to_str())
        .expect("a name")
        .to_owned();
    let prefix = format!("usal-run-{domain}-");
    assert!(
        name.starts_with(&prefix) && name.len() >= prefix.len() + 6,
        "{name}: the domain and a random part"
    );
    let mode = std::fs::metadata(&scratch)
        .expect("the scratch directory exists while the mission runs")
        .permissions()
        .mode();
    assert_eq!(mode & 0o777, 0o700, "{}: mode {mode:o}", scratch.display());
    l.expect(STEP, "vas started", |v| {
        v["event"] == "started" && v["service"] == "air/vas"
    });
    l.signal("INT");
    let status = l.wait_exit(STEP);
    l.drain();
    assert!(status.success(), "{status}\n{}", l.stderr_tail());
    assert!(!scratch.exists(), "{} left behind", scratch.display());
    assert_no_child_left(&l.pids());
}

/// `<mission security="off">`: the launcher says loudly that the run is not sealed, and so does
/// every node of it as it opens; nothing of the mission's seal is given to them.
#[test]
fn a_mission_run_with_security_off_says_so_at_start_and_in_every_node() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mission = demo_mission_with(
        dir.path(),
        "rover-unsealed.xml",
        &[(
            r#"<mission name="rover-demo""#,
            r#"<mission name="rover-unsealed" security="off""#,
        )],
    );
    let mut l = Launcher::start(&[mission.to_str().expect("a UTF-8 path"), "--speedup", "5"]);
    let unsealed = l.event(STEP, "unsealed");
    assert_eq!(unsealed["mission"], "rover-unsealed", "{unsealed}");
    assert!(
        !l.seen.iter().any(|v| v["event"] == "sealed"),
        "{:?}",
        l.seen
    );
    // Every service is up and talking once the FPMa has the plan and the vehicle moves.
    l.expect(STEP, "WAYPOINT_NAVIGATION", |v| {
        v["event"] == "state" && v["state"] == "WAYPOINT_NAVIGATION"
    });
    let warned = |service: &str| {
        l.stderr.lock().unwrap().lines().any(|line| {
            line.starts_with(&format!("[{service}]"))
                && line.contains("WARN")
                && line.contains("not sealed: any host on this node's networks")
        })
    };
    for service in ["air/vas", "air/fpma", "ground/fmo", "ground/fpmo"] {
        assert!(
            warned(service),
            "{service} did not warn that it is not sealed:\n{}",
            l.stderr_tail()
        );
    }
    l.signal("INT");
    let status = l.wait_exit(STEP);
    l.drain();
    assert!(status.success(), "{status}");
}

/// With `<station start="operator">` the launcher never presses Start: the plan loads and the
/// rover stays parked (well past the second after which `start="auto"` starts it) until the
/// pilot asks for WAYPOINT_NAVIGATION, here with `usal call`; then it flies the plan.
#[test]
fn with_start_by_the_operator_the_rover_waits_for_the_pilot() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mission = operator_mission(dir.path());
    let mut l = Launcher::start(&[
        mission.to_str().expect("a UTF-8 path"),
        "--until-complete",
        "--speedup",
        "20",
    ]);
    let domain = l.domain();
    let by = l.event(STEP, "start_by");
    assert_eq!(by["by"], "operator", "{by}");
    l.event(STEP, "plan_loaded");
    l.none_within(Duration::from_secs(4), "the rover started by itself", |v| {
        v["event"] == "navigation_kicked"
            || (v["event"] == "state" && v["state"] == "WAYPOINT_NAVIGATION")
    });
    press_start_as_the_pilot(&domain);
    l.expect(STEP, "WAYPOINT_NAVIGATION", |v| {
        v["event"] == "state" && v["state"] == "WAYPOINT_NAVIGATION"
    });
    let summary = l.completed();
    check_summary(&summary["summary"]);
    assert!(
        !l.seen.iter().any(|v| v["event"] == "navigation_kicked"),
        "the station pressed Start"
    );
    assert_no_child_left(&l.pids());
}

/// `<station start="operator">` after a VAS restart: the launcher does not bring the vehicle
/// back into the plan (no re-send, no Start); it says the return is the pilot's, and the rover
/// stays parked.
#[test]
fn with_start_by_the_operator_a_restarted_vas_waits_for_the_pilot() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mission = operator_mission(dir.path());
    let mut l = Launcher::start(&[mission.to_str().expect("a UTF-8 path"), "--speedup", "10"]);
    let domain = l.domain();
    let vas = l.expect(STEP, "vas started", |v| {
        v["event"] == "started" && v["service"] == "air/vas"
    });
    l.event(STEP, "plan_loaded");
    press_start_as_the_pilot(&domain);
    l.expect(FLIGHT, "waypoint 2", |v| {
        v["event"] == "waypoint" && v["n"].as_u64() >= Some(2)
    });
    signal(vas["pid"].as_u64().expect("a pid") as u32, "KILL");
    l.expect(STEP, "vas restarted", |v| {
        v["event"] == "started" && v["service"] == "air/vas" && v["restarts"] == 1
    });
    l.event(STEP, "recovery_left_to_operator");
    l.none_within(
        Duration::from_secs(4),
        "the launcher resumed the plan",
        |v| {
            v["event"] == "vas_recovered"
                || v["event"] == "navigation_kicked"
                || (v["event"] == "state" && v["state"] == "WAYPOINT_NAVIGATION")
        },
    );
}

/// The FMo's state (`/api/state`) as JSON, from its URL as `usal run`'s log prints it.
fn fmo_state(url: &str) -> Value {
    let (base, token) = url
        .split_once("/?token=")
        .expect("a token in the FMo's URL");
    let addr = base.trim_start_matches("http://");
    let mut conn = std::net::TcpStream::connect(addr).expect("the FMo answers");
    conn.set_read_timeout(Some(STEP)).expect("a read timeout");
    write!(
        conn,
        "GET /api/state HTTP/1.1\r\nHost: {addr}\r\nX-Station-Token: {}\r\nConnection: close\r\n\r\n",
        token.trim()
    )
    .expect("the request goes out");
    let mut reply = String::new();
    conn.read_to_string(&mut reply).expect("the FMo's reply");
    let body = reply.split_once("\r\n\r\n").map_or("", |(_, b)| b);
    serde_json::from_str(body).unwrap_or_else(|e| panic!("the FMo's state: {e}: {reply}"))
}

/// A vehicle fence the autopilot does not take (600 vertices, more than mavsim's fence
/// storage of 500: MAV_MISSION_NO_SPACE, as a small board answers) keeps the rover parked:
/// `usal run` prints the VAS's reason for refusing Start, the FMo shows the VAS's alarm, and
/// the rover never navigates.
#[test]
fn a_vehicle_fence_the_autopilot_refuses_keeps_the_rover_parked_and_says_why() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mission = demo_mission_with(dir.path(), "rover-big-fence.xml", &[]);
    let text = std::fs::read_to_string(&mission).expect("the mission");
    let from = text
        .find(r#"<fence maxDistance="300""#)
        .expect("the demo's vehicle fence");
    let to = from + text[from..].find("</fence>").expect("its end") + "</fence>".len();
    let pts: String = (0..600)
        .map(|i| {
            let a = f64::from(i) / 600.0 * std::f64::consts::TAU;
            let (n, e) = (250.0 * a.cos(), 250.0 * a.sin());
            format!(
                r#"<pt lat="{:.7}" lon="{:.7}"/>"#,
                41.275 + n / 111_195.0,
                1.987 + e / (111_195.0 * 41.275_f64.to_radians().cos())
            )
        })
        .collect();
    let big = format!(r#"<fence action="hold">{pts}</fence>"#);
    std::fs::write(&mission, format!("{}{big}{}", &text[..from], &text[to..]))
        .expect("write the mission");

    let mut l = Launcher::start(&[mission.to_str().expect("a UTF-8 path"), "--speedup", "5"]);
    let refused = l.expect(STEP, "Start refused for the fence", |v| {
        v["event"] == "navigation_refused"
            && v["reason"]
                .as_str()
                .is_some_and(|r| r.contains("did not take the fence"))
    });
    let reason = refused["reason"].as_str().unwrap_or_default();
    assert!(
        reason.contains("does not start without it") && reason.contains("fence transfer"),
        "{reason}"
    );
    l.none_within(Duration::from_secs(4), "the rover started", |v| {
        v["event"] == "state" && v["state"] == "WAYPOINT_NAVIGATION"
    });
    let url = l
        .stderr
        .lock()
        .unwrap()
        .lines()
        .find_map(|line| {
            line.split_once("[ground/fmo] FMO_URL=")
                .map(|(_, u)| u.trim().to_owned())
        })
        .expect("the FMo's URL in the merged log");
    let deadline = Instant::now() + STEP;
    loop {
        let state = fmo_state(&url).to_string();
        if state.contains("did not take the fence") {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "no fence alarm in the FMo: {state}"
        );
        std::thread::sleep(Duration::from_millis(200));
    }
    l.signal("INT");
    let status = l.wait_exit(STEP);
    l.drain();
    assert!(status.success(), "{status}\n{}", l.stderr_tail());
    assert_no_child_left(&l.pids());
}

#[test]
fn usal_says_its_version() {
    let out = Command::new(USAL)
        .arg("--version")
        .output()
        .expect("usal --version");
    assert!(out.status.success(), "{out:?}");
    assert_eq!(
        String::from_utf8_lossy(&out.stdout).trim(),
        format!("usal {}", env!("CARGO_PKG_VERSION"))
    );
}

/// A bad plan another tool sends into a running mission is refused by the FPMa and changes
/// nothing: the sender is told why, `usal run` says so and the mission flies on to its end (it
/// used to stop every service at the first `plan_rejected`, whoever's plan it was).
#[test]
fn a_bad_plan_sent_by_another_tool_is_refused_and_the_mission_flies_on() {
    let dir = tempfile::tempdir().expect("tempdir");
    let bad = dir.path().join("bad-plan.xml");
    std::fs::write(
        &bad,
        r#"<flightPlan name="bad"><mission><leg type="TF" fix="NOPE"/></mission></flightPlan>"#,
    )
    .expect("write the bad plan");
    let mut l = Launcher::start(&[
        "config/missions/rover-demo.xml",
        "--until-complete",
        "--speedup",
        "20",
    ]);
    let domain = l.domain();
    l.expect(STEP, "WAYPOINT_NAVIGATION", |v| {
        v["event"] == "state" && v["state"] == "WAYPOINT_NAVIGATION"
    });
    let bad_path = bad.to_str().expect("a UTF-8 path");
    // The sender hears the refusal itself: the FPMa loads a plan before its sink stores it.
    let (sent, said) = tool(&domain, &["send", bad_path, "--to", "rover1/fpma/plans"]);
    assert!(!sent, "a refused plan was reported sent: {said}");
    assert!(
        said.contains("refused the file") && said.contains("unknown fix `NOPE`"),
        "{said}"
    );
    let refused = l.expect(STEP, "the refusal noted", |v| v["event"] == "plan_refused");
    assert!(
        refused["reason"]
            .as_str()
            .is_some_and(|r| r.contains("unknown fix `NOPE`"))
            && refused["file"] == "bad-plan.xml",
        "{refused}"
    );
    let summary = l.completed();
    check_summary(&summary["summary"]);
    assert_no_child_left(&l.pids());
}

/// `usal run` killed with SIGKILL mid-flight (it can stop nothing itself) leaves no child
/// running: the kernel asks each to stop when the launcher dies.
#[test]
fn a_launcher_killed_with_sigkill_leaves_no_child() {
    let mut l = Launcher::start(&["config/missions/rover-demo.xml", "--speedup", "2"]);
    l.expect(STEP, "WAYPOINT_NAVIGATION", |v| {
        v["event"] == "state" && v["state"] == "WAYPOINT_NAVIGATION"
    });
    let pids = l.pids();
    assert!(pids.iter().all(|(_, p)| alive(*p)), "{pids:?}");
    signal(l.child.id(), "KILL");
    let _ = l.child.wait();
    // Nothing tells us when another process's child ends: look until all are gone, within the
    // services' own bound on stopping.
    let deadline = Instant::now() + Duration::from_secs(20);
    while pids.iter().any(|(_, p)| alive(*p)) && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(100));
    }
    assert_no_child_left(&pids);
}

#[test]
fn tools_see_a_running_mission_and_sigint_leaves_no_child() {
    let mut l = Launcher::start(&["config/missions/rover-demo.xml", "--speedup", "2"]);
    let domain = l.domain();
    l.expect(STEP, "WAYPOINT_NAVIGATION", |v| {
        v["event"] == "state" && v["state"] == "WAYPOINT_NAVIGATION"
    });

    let (ok, list) = tool(&domain, &["list"]);
    assert!(ok, "{list}");
    for needle in [
        "service vas",
        "service fpma",
        "service station",
        "rover1/vas/position",
        "rover1/vas/change_state",
        "rover1/vas/waypoint_reached",
        "rover1/fpma/progress",
        "rover1/fpma/plans",
        "rover1/fpma/load_plan",
    ] {
        assert!(list.contains(needle), "`usal list` lacks {needle}:\n{list}");
    }

    // Sealed with no configuration: another user (a fresh state directory, so no key) sees
    // none of the mission's items and cannot command its vehicle.
    let stranger = tempfile::tempdir().unwrap();
    let (_, list) = tool_with_state(Some(stranger.path()), &domain, &["list"]);
    assert!(
        !list.contains("rover1/"),
        "another user listed the sealed mission's items:\n{list}"
    );
    let (ok, answer) = tool_with_state(
        Some(stranger.path()),
        &domain,
        &["call", "rover1/vas/change_state", r#"{"to":"PARKING"}"#],
    );
    assert!(!ok, "another user's call was answered: {answer}");
    l.none_within(
        Duration::from_secs(1),
        "PARKING after another user's call",
        |v| v["event"] == "state" && v["state"] == "PARKING",
    );
    // Holding the domain key is not enough: the shipped mission's <access> lets only proven
    // identities command the vehicle, and a tool given the key file alone has none.
    let sealed = l.seen.iter().find(|v| v["event"] == "sealed");
    let key = sealed.expect("the sealed note, before the vehicle moved")["key"]
        .as_str()
        .expect("the domain key's path")
        .to_owned();
    let (ok, answer) = tool(
        &domain,
        &[
            "--key-file",
            &key,
            "call",
            "rover1/vas/change_state",
            r#"{"to":"PARKING"}"#,
        ],
    );
    assert!(
        !ok && answer.to_lowercase().contains("denied"),
        "a key holder without an identity was obeyed: {answer}"
    );
    l.none_within(
        Duration::from_secs(1),
        "PARKING after a call without an identity",
        |v| v["event"] == "state" && v["state"] == "PARKING",
    );

    let (ok, echo) = tool(&domain, &["echo", "rover1/vas/position", "--count", "2"]);
    assert!(ok, "{echo}");
    let samples: Vec<&str> = echo
        .lines()
        .filter(|l| l.starts_with("rover1/vas/position"))
        .collect();
    assert_eq!(samples.len(), 2, "{echo}");
    assert!(
        samples.iter().all(|s| s.contains("\"lat\":41.27")),
        "{echo}"
    );

    // `usal echo … | head -1`: the reader closes the pipe after one line; echo ends quietly.
    let mut echo = Command::new(USAL)
        .args(["--domain", &domain, "echo", "rover1/vas/position"])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("usal echo");
    let mut first = String::new();
    BufReader::new(echo.stdout.take().expect("piped stdout"))
        .read_line(&mut first)
        .expect("one echoed line");
    assert!(first.starts_with("rover1/vas/position"), "{first}");
    let deadline = Instant::now() + STEP;
    let status = loop {
        if let Ok(Some(status)) = echo.try_wait() {
            break status;
        }
        if Instant::now() >= deadline {
            let _ = echo.kill();
            let _ = echo.wait();
            panic!("usal echo kept running after its reader closed the pipe");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let mut err = String::new();
    echo.stderr
        .take()
        .expect("piped stderr")
        .read_to_string(&mut err)
        .expect("echo stderr");
    assert!(
        status.success() && !err.contains("panicked"),
        "{status}: {err}"
    );

    let (ok, answer) = tool(
        &domain,
        &["call", "rover1/vas/change_state", r#"{"to":"PARKING"}"#],
    );
    assert!(ok, "{answer}");
    assert!(
        answer.contains(r#""from":"WAYPOINT_NAVIGATION""#) && answer.contains(r#""to":"PARKING""#),
        "{answer}"
    );
    l.expect(STEP, "PARKING", |v| {
        v["event"] == "state" && v["state"] == "PARKING"
    });

    // Ctrl-C: every child stopped, none left.
    let pids = l.pids();
    l.signal("INT");
    let status = l.wait_exit(STEP);
    l.drain();
    assert!(status.success(), "{status}");
    let stopped = l.seen.iter().filter(|v| v["event"] == "stopped").count();
    assert_eq!(stopped, pids.len(), "{:?}", l.seen);
    assert_no_child_left(&pids);
}

#[test]
fn a_malformed_mission_file_names_element_and_line_and_starts_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.xml");
    std::fs::write(
        &bad,
        "<mission name=\"bad\">\n  <node name=\"air\">\n    <mavsim vehicle=\"rover\"/>\n    <vas vehicle=\"rover\" queueSize=\"five\"/>\n  </node>\n</mission>\n",
    )
    .unwrap();
    let out = Command::new(USAL)
        .args(["run", bad.to_str().unwrap(), "--until-complete"])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("bad.xml:4:5: <vas>:") && err.contains("queueSize"),
        "{err}"
    );
    assert!(!err.contains("started"), "{err}");

    std::fs::write(
        &bad,
        "<mission name=\"bad\">\n  <node name=\"air\">\n</mission>\n",
    )
    .unwrap();
    let out = Command::new(USAL)
        .args(["run", bad.to_str().unwrap()])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("bad.xml:3:") && err.contains("<node>"),
        "{err}"
    );
}

/// The failsafe rehearsal. Over a lossy radio the station first offers a plan that
/// leaves the field's geofence (refused), the radio goes silent mid-mission (the VAS holds,
/// then resumes) and the battery runs low (the plan's rule sends the rover to the approach);
/// the run ends with status 0 and a summary naming each failsafe that fired.
#[test]
fn the_rover_failsafe_mission_names_each_failsafe_that_fired() {
    let mut l = Launcher::start(&[
        "config/missions/rover-failsafe.xml",
        "--until-complete",
        "--speedup",
        "20",
    ]);
    let summary = l.event(FLIGHT * 2, "summary");
    let status = l.wait_exit(STEP);
    l.drain();
    assert!(status.success(), "{status}\n{}", l.stderr_tail());
    let s = &summary["summary"];
    assert_eq!(s["completed"], true, "{s}");
    let fired: Vec<(String, String)> = s["failsafes"]
        .as_array()
        .unwrap_or_else(|| panic!("no failsafes in {s}"))
        .iter()
        .map(|f| {
            (
                f["kind"].as_str().unwrap_or_default().to_owned(),
                f["action"].as_str().unwrap_or_default().to_owned(),
            )
        })
        .collect();
    let action = |kind: &str| {
        fired
            .iter()
            .find(|(k, _)| k == kind)
            .map(|(_, a)| a.as_str())
            .unwrap_or_else(|| panic!("no {kind} failsafe in {fired:?}"))
    };
    assert_eq!(action("fence"), "refused");
    assert_eq!(action("battery"), "rule low-battery");
    // Held if the rover was already driving when the radio went silent (on a machine slow
    // enough for the outage to come first, the VAS only reports it), resumed when it returned.
    match action("link-lost") {
        "hold" => assert_eq!(action("link-restored"), "resume", "{fired:?}"),
        other => assert_eq!(other, "continue", "{fired:?}"),
    }
    assert_no_child_left(&l.pids());
}
