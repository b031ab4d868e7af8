//! Flight safety in the field, in separate processes: `fpma run` + `vas` + `mavsim`.
//!
//! - Battery: mavsim drains a small battery; the VAS publishes it; the FPMa's `battery` follows
//!   it and the rover car-park plan's `low-battery` rule sends the rover to the approach.
//! - Pilot in command: a plan loaded while the operator drives (MANUAL_NAVIGATION, then
//!   DIRECTED) only waits, saying "press Start"; the operator's WAYPOINT_NAVIGATION flies it.
//! - Altitude references: with home at 584 m above sea level, a copter flies a plan written in
//!   MSL and one written relative to home; each reaches its waypoints at the height the plan
//!   means, and the FPMa's `alt` is measured from the plan's reference.

use std::path::Path;
use std::time::Duration;

use flightplan::api::{PlanEvent, PlanEventKind, PlanLoaded, PlanState, VarValue};
use marea::Node;
use tokio::process::Child;
use tokio::time::{timeout, Instant};
use usal_types::{
    Battery, FlightState, Position, StateChangeReply, StateChangeRequest, WaypointReached,
};

mod common;
use common::{ground, start_fpma, start_mavsim, start_vas};

/// Bound on each single wait.
const STEP: Duration = Duration::from_secs(30);
/// Bound on a whole flight.
const FLIGHT: Duration = Duration::from_secs(120);
/// Where mavsim starts (the car-park plan's HOME fix).
const HOME: (f64, f64) = (41.275, 1.987);
/// Home's altitude above sea level in the altitude tests: far from 0, so that MSL and
/// relative altitudes cannot be confused.
const HOME_ALT: f64 = 584.0;

/// mavsim, vas and fpma for one vehicle `rover1` on a domain of their own, and a ground node.
struct Flight {
    children: Vec<Child>,
    node: Node,
    _dir: tempfile::TempDir,
}

impl Flight {
    /// Starts the three processes; `sim_args` and `vehicle` (`rover`, `copter`) choose the
    /// vehicle, `fpma_vehicle` (`rover`, `aircraft`) the FPMa's.
    async fn start(name: &str, vehicle: &str, fpma_vehicle: &str, sim_args: &[&str]) -> Self {
        let dir = tempfile::tempdir().unwrap();
        let domain = format!("fpma-safety-{name}-{}", std::process::id());
        let mut args = vec!["--vehicle", vehicle];
        args.extend_from_slice(sim_args);
        let (sim, addr) = start_mavsim(&args).await;
        let vas = start_vas(
            &addr,
            &domain,
            &["--vehicle", vehicle, "--telemetry-hz", "10"],
        );
        let fpma = start_fpma(
            &domain,
            fpma_vehicle,
            &dir.path().join("plans"),
            &dir.path().join("state"),
            &[],
        );
        let node = ground(&domain).await;
        Self {
            children: vec![sim, vas, fpma],
            node,
            _dir: dir,
        }
    }

    async fn stop(self) {
        for mut c in self.children {
            let _ = c.start_kill();
            let _ = timeout(STEP, c.wait()).await;
        }
    }
}

fn number(s: &PlanState, name: &str) -> Option<f64> {
    s.vars.iter().find_map(|(n, v)| match v {
        VarValue::Number(x) if n == name => Some(*x),
        _ => None,
    })
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_carpark_low_battery_rule_fires_as_mavsim_drains_its_battery() {
    let home = format!("{},{},0", HOME.0, HOME.1);
    // 1.7 A at the plan's 2 m/s: 85 % of 60 mAh is gone after about 110 s of driving, in
    // the mission stage (the departure is 30 m).
    let f = Flight::start(
        "battery",
        "rover",
        "rover",
        &[
            "--speedup",
            "25",
            "--home",
            &home,
            "--battery-capacity-mah",
            "60",
            "--battery-wh-per-km",
            "2",
            "--battery-idle-a",
            "0.5",
        ],
    )
    .await;
    let gcs = f.node.service("fpmo").unwrap();
    let load = gcs
        .function::<String, PlanLoaded>("rover1/fpma/load_plan")
        .unwrap();
    let events = gcs
        .subscribe_event::<PlanEvent>("rover1/fpma/plan_event")
        .unwrap();
    let plan_state = gcs
        .subscribe_variable::<PlanState>("rover1/fpma/state")
        .unwrap();
    let battery = gcs
        .subscribe_variable::<Battery>("rover1/vas/battery")
        .unwrap();
    let ready = gcs
        .subscribe_variable::<flightplan::api::Readiness>("rover1/fpma/ready")
        .unwrap();
    let change = gcs
        .function::<StateChangeRequest, StateChangeReply>("rover1/vas/change_state")
        .unwrap();
    let flight_state = gcs
        .subscribe_variable::<FlightState>("rover1/vas/flight_state")
        .unwrap();
    assert!(load.wait_provider(STEP).await, "fpma not discovered");
    timeout(STEP, async {
        while flight_state.recv().await.expect("flight_state").value != FlightState::Parking {}
    })
    .await
    .expect("the VAS reached PARKING");
    // Full and disarmed before the flight.
    let b = battery.recv_timeout(STEP).await.expect("battery").value;
    assert_eq!(b.remaining, Some(100.0), "{b:?}");
    assert!((b.voltage - 12.6).abs() < 0.05, "{b:?}");

    let src = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../config/flightplans/rover-carpark.xml"),
    )
    .unwrap();
    load.call(&src, STEP)
        .await
        .expect("the car-park plan loads");
    // The operator starts it once the FPMa says it is ready.
    let from = common::start_when_ready(&ready, &change, STEP).await;
    assert_eq!(from, FlightState::Parking);

    let mut fired_at = None;
    let mut stages = Vec::new();
    let deadline = Instant::now() + FLIGHT;
    loop {
        let left = deadline.saturating_duration_since(Instant::now());
        let e = events
            .recv_timeout(left)
            .await
            .unwrap_or_else(|e| panic!("plan not completed ({e}); stages {stages:?}"))
            .value;
        match e.kind {
            PlanEventKind::EmergencyFired { rule } => {
                assert_eq!(rule, "low-battery");
                fired_at = Some(stages.len());
            }
            PlanEventKind::StageChanged { stage } => stages.push(format!("{stage:?}")),
            PlanEventKind::PlanCompleted => break,
            _ => {}
        }
    }
    let fired_at = fired_at.expect("the low-battery rule fired");
    assert_eq!(
        stages.get(fired_at).map(String::as_str),
        Some("Approach"),
        "the rule sent the rover to the approach: {stages:?}"
    );
    // The FPMa's `battery` followed the VAS's, below the rule's 15 %.
    let s = plan_state
        .recv_timeout(STEP)
        .await
        .expect("plan state")
        .value;
    let fpma_battery = number(&s, "battery").expect("battery variable");
    assert!(fpma_battery < 15.0, "{s:?}");
    let b = battery.recv_timeout(STEP).await.expect("battery").value;
    assert!(b.remaining.is_some_and(|r| r < 15.0), "{b:?}");
    assert!(
        b.voltage < 12.6 - 1.5,
        "the voltage sags with the charge: {b:?}"
    );
    assert!(b.current.is_some_and(|a| a > 0.0), "{b:?}");
    f.stop().await;
}

/// A two-waypoint copter plan north of home at `alt` in `alt_ref`.
fn copter_plan(alt_ref: &str, alt: f64) -> String {
    format!(
        r#"<?xml version="1.0" encoding="UTF-8"?>
<flightPlan name="heights-{alt_ref}" vehicle="aircraft" altRef="{alt_ref}" defaultSpeed="5">
  <fixes>
    <fix id="A" lat="{a}" lon="{lon}" alt="{alt}"/>
    <fix id="B" lat="{b}" lon="{lon}" alt="{alt}"/>
  </fixes>
  <mission>
    <leg type="IF" fix="A"/>
    <leg type="TF" fix="B"/>
  </mission>
</flightPlan>"#,
        // 111 m apart: aircraft waypoints closer than the FPMa's minimum distance are merged.
        a = HOME.0 + 0.001,
        b = HOME.0 + 0.002,
        lon = HOME.1,
    )
}

/// Flies `plan` on a copter whose home is at [`HOME_ALT`]; returns the VAS's position as each
/// waypoint is reported reached (after a take-off that must reach `climb_to` above home), and
/// the values the FPMa's `alt` took after the flight until
/// it came within 2 m of `want_fpma_alt`.
async fn fly_copter(
    name: &str,
    plan: &str,
    climb_to: f64,
    want_fpma_alt: f64,
) -> (Vec<Position>, Vec<f64>) {
    let home = format!("{},{},{HOME_ALT}", HOME.0, HOME.1);
    let f = Flight::start(
        name,
        "copter",
        "aircraft",
        &["--speedup", "10", "--home", &home],
    )
    .await;
    let gcs = f.node.service("fpmo").unwrap();
    let load = gcs
        .function::<String, PlanLoaded>("rover1/fpma/load_plan")
        .unwrap();
    let change = gcs
        .function::<StateChangeRequest, StateChangeReply>("rover1/vas/change_state")
        .unwrap();
    let reached = gcs
        .subscribe_event::<WaypointReached>("rover1/vas/waypoint_reached")
        .unwrap();
    let position = gcs
        .subscribe_variable::<Position>("rover1/vas/position")
        .unwrap();
    let plan_state = gcs
        .subscribe_variable::<PlanState>("rover1/fpma/state")
        .unwrap();
    let flight_state = gcs
        .subscribe_variable::<FlightState>("rover1/vas/flight_state")
        .unwrap();
    assert!(load.wait_provider(STEP).await, "fpma not discovered");
    assert!(change.wait_provider(STEP).await, "vas not discovered");
    timeout(STEP, async {
        while flight_state.recv().await.expect("flight_state").value != FlightState::Parking {}
    })
    .await
    .expect("the VAS reached PARKING");
    load.call(&plan.to_owned(), STEP)
        .await
        .expect("the plan loads");
    // The FPMa queues the waypoints; the operator takes off (to the first waypoint's height)
    // and starts the navigation.
    let queued = timeout(STEP, async {
        loop {
            if !plan_state
                .recv()
                .await
                .expect("plan state")
                .value
                .queued
                .is_empty()
            {
                return;
            }
        }
    })
    .await;
    assert!(queued.is_ok(), "the FPMa queued no waypoint");
    let to = |to| StateChangeRequest { to };
    change
        .call(&to(FlightState::TakeOff), STEP)
        .await
        .expect("TAKE_OFF");
    // TAKE_OFF climbs to the first waypoint's height above home (an MSL altitude less home's).
    let climbed = timeout(STEP, async {
        loop {
            let p = position.recv().await.expect("position").value;
            if p.alt_rel >= climb_to - 0.5 {
                return p;
            }
        }
    })
    .await;
    assert!(
        climbed.is_ok(),
        "the copter did not climb to {climb_to} m above home"
    );
    let mut out = Vec::new();
    // The FPMa never changes the flight state by itself (the pilot is in command): airborne
    // with the plan queued, the copter is still in TAKE_OFF, until the operator starts
    // navigating.
    let mut seen = Vec::new();
    while let Some(s) = flight_state.try_recv() {
        seen.push(s.expect("flight_state").value);
    }
    assert!(
        !seen.contains(&FlightState::WaypointNavigation),
        "the VAS went to WAYPOINT_NAVIGATION without the operator: {seen:?}"
    );
    let reply = change
        .call(&to(FlightState::WaypointNavigation), STEP)
        .await
        .expect("the operator's WAYPOINT_NAVIGATION");
    assert_eq!(
        reply.from,
        FlightState::TakeOff,
        "the FPMa switched the VAS by itself"
    );
    while out.len() < 2 {
        let r = timeout(STEP, reached.recv())
            .await
            .unwrap_or_else(|_| panic!("no waypoint reached after {out:?}"))
            .expect("waypoint_reached");
        assert_eq!(r.value.seq, out.len() as u64, "{:?}", r.value);
        let p = position.recv_timeout(STEP).await.expect("position").value;
        out.push(p);
    }
    // The FPMa's `alt` settles at the height flown, in the plan's reference.
    let mut alts = Vec::new();
    let _ = timeout(Duration::from_secs(5), async {
        loop {
            let s = plan_state.recv().await.expect("plan state").value;
            if let Some(a) = number(&s, "alt") {
                alts.push(a);
                if (a - want_fpma_alt).abs() < 2.0 {
                    return;
                }
            }
        }
    })
    .await;
    f.stop().await;
    (out, alts)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn msl_and_relative_plans_reach_their_heights_with_home_at_584_m() {
    // 634 m above the sea is 50 m above this home.
    let (reached, alts) = fly_copter("msl", &copter_plan("MSL", 634.0), 50.0, 634.0).await;
    for p in reached {
        assert!((p.alt - 634.0).abs() < 1.5, "MSL plan: {p:?}");
        assert!((p.alt_rel - 50.0).abs() < 1.5, "MSL plan: {p:?}");
    }
    assert!(
        alts.last().is_some_and(|a| (a - 634.0).abs() < 2.0),
        "the FPMa's alt is MSL: {alts:?}"
    );
    // 30 m above home is 614 m above the sea.
    let (reached, alts) = fly_copter("rel", &copter_plan("REL", 30.0), 30.0, 30.0).await;
    for p in reached {
        assert!((p.alt_rel - 30.0).abs() < 1.5, "relative plan: {p:?}");
        assert!(
            (p.alt - (HOME_ALT + 30.0)).abs() < 1.5,
            "relative plan: {p:?}"
        );
    }
    assert!(
        alts.last().is_some_and(|a| (a - 30.0).abs() < 2.0),
        "the FPMa's alt is above home: {alts:?}"
    );
}

/// The FPMa never takes the vehicle from the operator: a plan loaded in MANUAL_NAVIGATION
/// fills the queue and waits ("press Start") while the operator drives, also through a change
/// to DIRECTED; the operator's WAYPOINT_NAVIGATION starts it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_plan_loaded_while_the_operator_drives_waits_for_start() {
    let home = format!("{},{},0", HOME.0, HOME.1);
    let f = Flight::start(
        "pic",
        "rover",
        "rover",
        &["--speedup", "10", "--home", &home],
    )
    .await;
    let gcs = f.node.service("fpmo").unwrap();
    let load = gcs
        .function::<String, PlanLoaded>("rover1/fpma/load_plan")
        .unwrap();
    let change = gcs
        .function::<StateChangeRequest, StateChangeReply>("rover1/vas/change_state")
        .unwrap();
    let ready = gcs
        .subscribe_variable::<flightplan::api::Readiness>("rover1/fpma/ready")
        .unwrap();
    let reached = gcs
        .subscribe_event::<WaypointReached>("rover1/vas/waypoint_reached")
        .unwrap();
    let flight_state = gcs
        .subscribe_variable::<FlightState>("rover1/vas/flight_state")
        .unwrap();
    assert!(load.wait_provider(STEP).await, "fpma not discovered");
    assert!(change.wait_provider(STEP).await, "vas not discovered");
    timeout(STEP, async {
        while flight_state.recv().await.expect("flight_state").value != FlightState::Parking {}
    })
    .await
    .expect("the VAS reached PARKING");
    let to = |to| StateChangeRequest { to };
    change
        .call(&to(FlightState::ManualNavigation), STEP)
        .await
        .expect("MANUAL_NAVIGATION");
    let src = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../config/flightplans/rover-carpark.xml"),
    )
    .unwrap();
    let loaded = load.call(&src, STEP).await.expect("the plan loads");
    assert_eq!(loaded.navigation_refused, None);
    let r = timeout(STEP, async {
        loop {
            let r = ready.recv().await.expect("ready").value;
            if r.ready {
                return r;
            }
        }
    })
    .await
    .expect("the FPMa never said press Start");
    assert!(r.text.contains("press Start"), "{r:?}");
    // The operator keeps driving, then changes to DIRECTED: the plan still only waits.
    let reply = change
        .call(&to(FlightState::Directed), STEP)
        .await
        .expect("DIRECTED");
    assert_eq!(
        reply.from,
        FlightState::ManualNavigation,
        "the FPMa switched the state"
    );
    let mut seen = Vec::new();
    while let Some(s) = flight_state.try_recv() {
        seen.push(s.expect("flight_state").value);
    }
    assert!(
        !seen.contains(&FlightState::WaypointNavigation),
        "WAYPOINT_NAVIGATION without the operator: {seen:?}"
    );
    let reply = change
        .call(&to(FlightState::WaypointNavigation), STEP)
        .await
        .expect("the operator's Start");
    assert_eq!(reply.from, FlightState::Directed);
    let r = reached
        .recv_timeout(STEP)
        .await
        .expect("a waypoint reached");
    assert_eq!(r.value.seq, 0);
    timeout(STEP, async {
        while ready.recv().await.expect("ready").value.ready {}
    })
    .await
    .expect("still ready while flying");
    f.stop().await;
}
