//! A restarted FPMa resumes its plan where it was: `fpma run` + `vas` + `mavsim` as separate
//! processes fly `config/flightplans/rover-demo.xml`, loaded from the ground through
//! `load_plan`; the FPMa is killed (SIGKILL) mid-plan and started again with the same
//! arguments (no plan among them: only what it persisted can give it one). It must go on from
//! the persisted progress: the plan completes and mavsim flies the plan's waypoints once each,
//! in order (at most the one target the VAS was driving to at the restart reached twice in a
//! row, which the VAS queue's "a new queue follows" allows), not again from HOME.
//!
//! Then a corrupt state file: the FPMa logs it, sets it aside and starts clean (it answers
//! calls), never panics.

use std::path::{Path, PathBuf};
use std::time::Duration;

use flightplan::api::{CommandAck, PlanLoaded, Progress};
use tokio::process::Child;
use tokio::time::{timeout, Instant};
use usal_types::{FlightState, StateChangeReply, StateChangeRequest, WaypointReached};

mod common;
use common::{
    close, ground, kill, sim_reached, start_fpma, start_mavsim, start_vas, start_when_ready,
};

/// Bound on each single wait.
const STEP: Duration = Duration::from_secs(20);
/// Bound on the whole flight.
const FLIGHT: Duration = Duration::from_secs(120);
const HOME: (f64, f64) = (41.275, 1.987);

fn plan_path() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../config/flightplans/rover-demo.xml")
}

/// mavsim, then the VAS on it; returns them and mavsim's log.
async fn vehicle(dir: &Path, domain: &str) -> (Child, Child, PathBuf) {
    let log = dir.join("sim.jsonl");
    let (sim, addr) = start_mavsim(&[
        "--speedup",
        "10",
        "--home",
        &format!("{},{},0", HOME.0, HOME.1),
        "--log",
        log.to_str().unwrap(),
    ])
    .await;
    let vas = start_vas(&addr, domain, &["--queue-size", "5"]);
    (sim, vas, log)
}

fn fpma(domain: &str, state: &Path, plans: &Path) -> Child {
    start_fpma(domain, "rover", plans, state, &["--lookahead", "8"])
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_fpma_resumes_its_plan_where_it_was() {
    let dir = tempfile::tempdir().unwrap();
    let domain = format!("fpma-restart-{}", std::process::id());
    let (sim, vas, log) = vehicle(dir.path(), &domain).await;
    let state_dir = dir.path().join("state");
    let plans = dir.path().join("plans");
    let plan = plan_path();

    let node = ground(&domain).await;
    let gcs = node.service("fmo").unwrap();
    let reached = gcs
        .subscribe_event::<WaypointReached>("rover1/vas/waypoint_reached")
        .unwrap();
    let progress = gcs
        .subscribe_variable::<Progress>("rover1/fpma/progress")
        .unwrap();
    let state = gcs
        .subscribe_variable::<FlightState>("rover1/vas/flight_state")
        .unwrap();
    let change_state = gcs
        .function::<StateChangeRequest, StateChangeReply>("rover1/vas/change_state")
        .unwrap();
    let load = gcs
        .function::<String, PlanLoaded>("rover1/fpma/load_plan")
        .unwrap();
    assert!(change_state.wait_provider(STEP).await, "VAS not discovered");
    // The VAS is configured (PARKING) before the FPMa asks it to navigate.
    timeout(STEP, async {
        while state.recv().await.expect("flight_state").value != FlightState::Parking {}
    })
    .await
    .expect("the VAS never reached PARKING");

    // First run: the plan is loaded from the ground; the operator starts it when the FPMa
    // says it is ready (the FPMa never changes the flight state).
    let ready = gcs
        .subscribe_variable::<flightplan::api::Readiness>("rover1/fpma/ready")
        .unwrap();
    let first = fpma(&domain, &state_dir, &plans);
    assert!(load.wait_provider(STEP).await, "fpma not discovered");
    // A small round trip first, so the session is acknowledged before the plan is sent (as
    // in end_to_end.rs).
    let skip = gcs
        .function::<(), CommandAck>("rover1/fpma/skip_leg")
        .unwrap();
    assert!(skip.wait_provider(STEP).await, "skip_leg not discovered");
    let e = skip.call(&(), STEP).await.unwrap_err().to_string();
    assert!(e.contains("no plan is loaded"), "{e}");
    let src = std::fs::read_to_string(&plan).unwrap();
    let loaded = load.call(&src, STEP).await.expect("load_plan");
    assert_eq!(loaded.name, "rover-demo");
    let from = start_when_ready(&ready, &change_state, STEP).await;
    assert_eq!(from, FlightState::Parking);
    // Kill it once a few waypoints were reached, mid-plan.
    for _ in 0..4 {
        reached.recv_timeout(STEP).await.expect("waypoint reached");
    }
    kill(first).await;
    let before = sim_reached(&log).len();
    let persisted: serde_json::Value = serde_json::from_slice(
        &std::fs::read(state_dir.join("fpma-state.json")).expect("no state persisted"),
    )
    .expect("the state file is JSON");
    assert!(
        persisted["state"]["last_reached"].as_u64() >= Some(1),
        "progress not persisted: {}",
        persisted["state"]["last_reached"]
    );

    // Second run, same arguments.
    let second = fpma(&domain, &state_dir, &plans);
    // The vehicle state is the operator's: if the VAS left WAYPOINT_NAVIGATION while the
    // FPMa was down (its queue ran out), the operator puts it back; the FPMa does not.
    let deadline = Instant::now() + FLIGHT;
    let mut completed = false;
    while Instant::now() < deadline && !completed {
        tokio::select! {
            p = progress.recv() => {
                let p = p.expect("progress").value;
                completed = p.completed;
            }
            s = state.recv() => {
                let s = s.expect("flight_state").value;
                if s == FlightState::Parking && !completed {
                    let _ = change_state
                        .call(&StateChangeRequest { to: FlightState::WaypointNavigation }, STEP)
                        .await;
                }
            }
            _ = tokio::time::sleep_until(deadline) => {}
        }
    }
    assert!(completed, "the plan did not complete after the restart");

    // What mavsim flew: the plan's waypoints, each once, in order.
    let vehicle = flightplan::vehicle::VehicleParams::rover();
    let parsed = flightplan::parse::parse_plan(&src).unwrap();
    let want: Vec<(f64, f64)> = flightplan::exec::expand_nominal(parsed, vehicle)
        .unwrap()
        .iter()
        .map(|w| (w.lat, w.lon))
        .collect();
    let flown = sim_reached(&log);
    let mut dedup = flown.clone();
    dedup.dedup_by(|a, b| close(*a, *b));
    let repeats = flown.len() - dedup.len();
    eprintln!(
        "{} waypoints flown ({before} before the restart), {repeats} reached twice in a row",
        flown.len()
    );
    assert!(
        before > 0 && before < want.len(),
        "killed mid-plan: {before}"
    );
    assert_eq!(dedup.len(), want.len(), "flown {flown:?}\nplanned {want:?}");
    assert!(
        dedup.iter().zip(&want).all(|(a, b)| close(*a, *b)),
        "flown {flown:?}\nplanned {want:?}"
    );
    assert!(repeats <= 1, "{repeats} waypoints repeated: {flown:?}");

    kill(second).await;
    kill(vas).await;
    kill(sim).await;
    node.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_corrupt_state_file_gives_a_clean_start() {
    let dir = tempfile::tempdir().unwrap();
    let domain = format!("fpma-corrupt-{}", std::process::id());
    let state_dir = dir.path().join("state");
    std::fs::create_dir_all(&state_dir).unwrap();
    let file = state_dir.join("fpma-state.json");
    std::fs::write(&file, b"{\"format\":1,\"state\":{\"source\":").unwrap();
    let fpma = fpma(&domain, &state_dir, &dir.path().join("plans"));

    let node = ground(&domain).await;
    let gcs = node.service("fpmo").unwrap();
    let skip = gcs
        .function::<(), CommandAck>("rover1/fpma/skip_leg")
        .unwrap();
    assert!(skip.wait_provider(STEP).await, "fpma not up");
    // Up, with no plan: a clean start.
    let e = skip.call(&(), STEP).await.unwrap_err().to_string();
    assert!(e.contains("no plan is loaded"), "{e}");
    assert!(!file.exists(), "corrupt file left in place");
    assert!(state_dir.join("fpma-state.json.corrupt").exists());

    kill(fpma).await;
    node.shutdown().await;
}
