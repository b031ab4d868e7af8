//! End to end, in separate processes: `fpma run` + `vas` + `mavsim` fly the rover example plan
//! (`config/flightplans/rover-carpark.xml`), sent as a file. Mid-flight the test skips the hold,
//! widens the scan's spacing (`modify_leg`) and sets the variable that ends the waiting hold;
//! mavsim's log must show the waypoints the VAS was given, in order; those must be, in order,
//! the waypoints an executive of the test's own produces for the same plan and commands; and the
//! plan completes.

use std::path::Path;
use std::time::Duration;

use flightplan::api::{
    CommandAck, ModifyLeg, PlanEvent, PlanEventKind, PlanRejected, Progress, SetVar,
};
use flightplan::api::{PlanLoaded, VarValue};
use marea::SendFileOptions;
use tokio::time::{timeout, Instant};
use usal_types::{FlightState, StateChangeReply, StateChangeRequest, WaypointReached};

mod common;
use common::{
    close, ground, kill, sim_reached, start_fpma, start_mavsim, start_vas, start_when_ready,
};

/// Bound on each single wait.
const STEP: Duration = Duration::from_secs(20);
/// Bound on the whole flight.
const FLIGHT: Duration = Duration::from_secs(90);
/// The plan's HOME fix: where mavsim starts.
const HOME: (f64, f64) = (41.275, 1.987);
const M_PER_DEG_LAT: f64 = 111_320.0;

/// Distinct track latitudes of scan waypoints, as metres apart, sorted.
fn track_gaps(points: &[(f64, f64)]) -> Vec<f64> {
    let mut lats: Vec<f64> = points.iter().map(|p| p.0).collect();
    lats.sort_by(f64::total_cmp);
    lats.dedup_by(|a, b| (*a - *b).abs() * M_PER_DEG_LAT < 0.5);
    lats.windows(2)
        .map(|w| (w[1] - w[0]) * M_PER_DEG_LAT)
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fpma_vas_mavsim_fly_the_rover_plan_with_changes_in_flight() {
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("sim.jsonl");
    let domain = format!("fpma-e2e-{}", std::process::id());

    let (sim, addr) = start_mavsim(&[
        "--speedup",
        "25",
        "--home",
        &format!("{},{},0", HOME.0, HOME.1),
        "--log",
        log.to_str().unwrap(),
    ])
    .await;
    let vas = start_vas(&addr, &domain, &["--queue-size", "5"]);
    let fpma = start_fpma(
        &domain,
        "rover",
        &dir.path().join("plans"),
        &dir.path().join("state"),
        &["--lookahead", "8"],
    );

    // The ground station.
    let node = ground(&domain).await;
    let gcs = node.service("fpmo").unwrap();
    let load = gcs
        .function::<String, PlanLoaded>("rover1/fpma/load_plan")
        .unwrap();
    let skip = gcs
        .function::<(), CommandAck>("rover1/fpma/skip_leg")
        .unwrap();
    let modify = gcs
        .function::<ModifyLeg, CommandAck>("rover1/fpma/modify_leg")
        .unwrap();
    let set_var = gcs
        .function::<SetVar, CommandAck>("rover1/fpma/set_var")
        .unwrap();
    let events = gcs
        .subscribe_event::<PlanEvent>("rover1/fpma/plan_event")
        .unwrap();
    let rejected = gcs
        .subscribe_event::<PlanRejected>("rover1/fpma/plan_rejected")
        .unwrap();
    let progress = gcs
        .subscribe_variable::<Progress>("rover1/fpma/progress")
        .unwrap();
    let vas_reached = gcs
        .subscribe_event::<WaypointReached>("rover1/vas/waypoint_reached")
        .unwrap();
    let state = gcs
        .subscribe_variable::<FlightState>("rover1/vas/flight_state")
        .unwrap();
    let ready = gcs
        .subscribe_variable::<flightplan::api::Readiness>("rover1/fpma/ready")
        .unwrap();
    let change = gcs
        .function::<StateChangeRequest, StateChangeReply>("rover1/vas/change_state")
        .unwrap();
    // The FPMa declares its items one by one: wait for each function used below.
    assert!(load.wait_provider(STEP).await, "fpma not discovered");
    assert!(skip.wait_provider(STEP).await, "skip_leg not discovered");
    assert!(
        modify.wait_provider(STEP).await,
        "modify_leg not discovered"
    );
    assert!(set_var.wait_provider(STEP).await, "set_var not discovered");
    let wait_state = |want: FlightState| {
        let state = &state;
        async move {
            timeout(STEP, async {
                while state.recv().await.expect("flight_state").value != want {}
            })
            .await
            .unwrap_or_else(|_| panic!("the VAS never reached {want}"));
        }
    };
    wait_state(FlightState::Parking).await;

    // A small round trip first, so the session is acknowledged before a ~3 KB plan is sent
    // (the same marea bug as above).
    let e = skip.call(&(), STEP).await.unwrap_err().to_string();
    assert!(e.contains("no plan is loaded"), "{e}");

    // A bad plan, through the function and as a file: refused with the line.
    let src = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../config/flightplans/rover-carpark.xml"),
    )
    .unwrap();
    let bad = src.replace(r#"fix="APP""#, r#"fix="NOWHERE""#);
    let e = load.call(&bad, STEP).await.unwrap_err().to_string();
    assert!(
        e.contains("plan:") && e.contains("unknown fix `NOWHERE`"),
        "{e}"
    );
    let bad_file = dir.path().join("broken.xml");
    std::fs::write(&bad_file, &bad).unwrap();
    // The sender hears the refusal (the plan is loaded before the sink stores it), and the
    // stations see it as `plan_rejected`.
    let sent = gcs
        .send_file(&bad_file, "rover1/fpma/plans", SendFileOptions::default())
        .wait()
        .await;
    match sent {
        Err(marea::FileSendError::Rejected { reason, .. }) => assert!(
            reason.starts_with("broken.xml:") && reason.contains("NOWHERE"),
            "{reason}"
        ),
        other => panic!("the broken plan was not refused to its sender: {other:?}"),
    }
    let r = rejected.recv_timeout(STEP).await.expect("plan_rejected");
    assert!(
        r.value.reason.starts_with("broken.xml:") && r.value.reason.contains("NOWHERE"),
        "{:?}",
        r.value
    );

    // The real plan, as a file: it waits for the operator's start.
    let plan_file = dir.path().join("rover-carpark.xml");
    std::fs::write(&plan_file, &src).unwrap();
    let started = Instant::now();
    gcs.send_file(&plan_file, "rover1/fpma/plans", SendFileOptions::default())
        .wait()
        .await
        .expect("sending the plan");

    // Follow the executive; change the plan in flight.
    let mut reached: Vec<(u64, u64, String)> = Vec::new(); // (version, seq, leg)
    let mut acks = Vec::new();
    let (mut skipped, mut modified, mut released) = (false, false, false);
    let mut loaded = false;
    // How many waypoints the executive had reached when it applied the skip and the change
    // (its events come in order, so this is exact even if a command arrived a waypoint late).
    let (mut skip_at, mut modify_at) = (None, None);
    let deadline = Instant::now() + FLIGHT;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let e = events
            .recv_timeout(left)
            .await
            .unwrap_or_else(|e| panic!("plan not completed ({e}); reached {reached:?}"))
            .value;
        match e.kind {
            PlanEventKind::PlanLoaded { name } => {
                assert_eq!(name, "castelldefels-carpark");
                loaded = true;
                // "Plan ready, press Start": the operator does.
                let from = start_when_ready(&ready, &change, STEP).await;
                assert_eq!(
                    from,
                    FlightState::Parking,
                    "the FPMa changed the state itself"
                );
            }
            PlanEventKind::WaypointReached { seq, leg } => {
                reached.push((e.version, seq, leg.clone()));
                if leg == "hold" && !skipped {
                    skipped = true;
                    acks.push(skip.call(&(), STEP).await.expect("skip_leg"));
                }
                let area = reached.iter().filter(|r| r.2 == "area").count();
                if leg == "area" && area == 3 && !modified {
                    modified = true;
                    let change = ModifyLeg {
                        leg: "area".into(),
                        changes: vec![("spacing".into(), "10".into())],
                    };
                    acks.push(modify.call(&change, STEP).await.expect("modify_leg"));
                }
                if leg == "wait" && !released {
                    released = true;
                    let v = SetVar {
                        name: "inspect".into(),
                        value: VarValue::Bool(true),
                    };
                    acks.push(set_var.call(&v, STEP).await.expect("set_var"));
                }
            }
            PlanEventKind::LegCompleted { leg, skipped: true } if leg == "hold" => {
                skip_at = Some(reached.len());
            }
            PlanEventKind::PlanModified { leg } if leg == "area" => {
                modify_at = Some(reached.len());
            }
            PlanEventKind::PlanCompleted => break,
            _ => {}
        }
    }
    assert!(loaded && skipped && modified && released, "{reached:?}");
    eprintln!("flown in {:?}", started.elapsed());
    assert_eq!(
        acks[0].leg.as_deref(),
        Some("area"),
        "skip_leg ended the hold"
    );
    assert_eq!(acks[1].version, 2, "modify_leg made version 2");

    // Progress says so.
    timeout(STEP, async {
        loop {
            let p = progress.recv().await.expect("progress").value;
            if p.completed {
                assert_eq!(p.fraction, 1.0);
                assert_eq!(p.version, 2);
                assert!(p.flown_m > 300.0, "{p:?}");
                return;
            }
        }
    })
    .await
    .expect("progress 1.0");

    // The executive's reports: in order, the stages as planned, the hold cut short.
    let legs: Vec<&str> = reached.iter().map(|r| r.2.as_str()).collect();
    let mut order: Vec<&str> = legs.clone();
    order.dedup();
    assert_eq!(
        order,
        [
            "departure.1",
            "departure.2",
            "hold",
            "area",
            "laps.1",
            "laps.2",
            "laps.1",
            "laps.2",
            "wait",
            "approach.1",
            "approach.2"
        ],
        "{reached:?}"
    );
    assert!(
        legs.iter().filter(|l| **l == "hold").count() < 5,
        "hold skipped"
    );
    assert!(reached.windows(2).all(|w| w[0].1 < w[1].1), "seqs increase");

    // The VAS's reports: every one of the executive's, plus the targets it could not take back
    // at a clear (at most one per change), all reached once, in order.
    let last_seq = reached.last().unwrap().1;
    let mut vas_seen: Vec<WaypointReached> = Vec::new();
    timeout(STEP, async {
        while vas_seen.last().map(|w| w.seq) != Some(last_seq) {
            vas_seen.push(vas_reached.recv().await.expect("vas reached").value);
        }
    })
    .await
    .expect("the VAS's reports");
    let exec_seqs: Vec<u64> = reached.iter().map(|r| r.1).collect();
    let vas_seqs: Vec<u64> = vas_seen.iter().map(|w| w.seq).collect();
    let extra: Vec<u64> = vas_seqs
        .iter()
        .copied()
        .filter(|s| !exec_seqs.contains(s))
        .collect();
    assert!(
        exec_seqs.iter().all(|s| vas_seqs.contains(s)),
        "{exec_seqs:?} / {vas_seqs:?}"
    );
    assert!(extra.len() <= 3, "abandoned targets {extra:?}");
    assert!(vas_seqs.windows(2).all(|w| w[0] < w[1]), "{vas_seqs:?}");

    // mavsim flew exactly those points, in order.
    wait_state(FlightState::Parking).await;
    let flown = sim_reached(&log);
    let given: Vec<(f64, f64)> = vas_seen.iter().map(|w| (w.lat, w.lon)).collect();
    assert_eq!(flown.len(), given.len(), "{flown:?}\n{given:?}");
    assert!(
        flown.iter().zip(&given).all(|(a, b)| close(*a, *b)),
        "{flown:?}\n{given:?}"
    );
    // Starts at HOME, ends at HOME, via the fixes of the plan.
    assert!(close(flown[0], HOME) && close(*flown.last().unwrap(), HOME));

    // The expected waypoints: the plan flown by an executive of our own, given the same
    // commands after the same waypoints. Every waypoint the FPMa's executive counted as
    // reached is, in order, where that one says it should be (mavsim flew exactly these, above,
    // plus at most one abandoned target per change).
    let plan = flightplan::check::load(&src, &flightplan::vehicle::VehicleParams::rover()).unwrap();
    let mut twin = flightplan::exec::Executive::from_checked(plan);
    let (skip_at, modify_at) = (skip_at.expect("skip seen"), modify_at.expect("modify seen"));
    let mut released_twin = false;
    for (i, (version, seq, leg)) in reached.iter().enumerate() {
        if i == skip_at {
            twin.skip_leg().unwrap();
        }
        if i == modify_at {
            twin.modify_leg("area", &[("spacing".into(), "10".into())])
                .unwrap();
        }
        let want = twin
            .next_waypoints(1)
            .pop()
            .expect("the twin has a waypoint");
        let got = vas_seen
            .iter()
            .find(|w| w.seq == *seq)
            .expect("the VAS reported it");
        assert!(
            close((got.lat, got.lon), (want.lat, want.lon)) && *leg == want.leg,
            "waypoint {i} (seq {seq}, v{version}): flown {got:?}, expected {want:?}"
        );
        assert_eq!(*version, want.version, "waypoint {i}");
        twin.waypoint_reached(want.version, want.seq).unwrap();
        // `inspect` was set on the hold's first waypoint; it ends the hold at its next fix
        // crossing, three corners on, however late it arrived within the circuit.
        if leg == "wait" && !released_twin {
            released_twin = true;
            twin.set_var("inspect", flightplan::expr::Value::Bool(true))
                .unwrap();
        }
    }
    assert!(
        twin.state().completed,
        "the twin's plan ends where the FPMa's did"
    );

    // The scan: 6 m between tracks before the change, 10 m after.
    let scan = |version: u64| -> Vec<(f64, f64)> {
        vas_seen
            .iter()
            .filter(|w| {
                w.leg == "area"
                    && reached
                        .iter()
                        .any(|r| r.1 == w.seq && r.0 == version && r.2 == "area")
            })
            .map(|w| (w.lat, w.lon))
            .collect()
    };
    let v2 = track_gaps(&scan(2));
    assert!(v2.len() >= 2, "{v2:?}");
    assert!(
        v2.iter().all(|g| (g - 10.0).abs() < 0.5),
        "spacing 10: {v2:?}"
    );
    let v1 = track_gaps(&scan(1));
    eprintln!(
        "{} waypoints reached, {} abandoned targets {extra:?}; track gaps v1 {v1:?} v2 {v2:?}",
        reached.len(),
        extra.len()
    );
    assert!(
        v1.iter().all(|g| (g - 6.0).abs() < 0.5),
        "spacing 6: {v1:?}"
    );

    kill(fpma).await;
    kill(vas).await;
    kill(sim).await;
    node.shutdown().await;
}
