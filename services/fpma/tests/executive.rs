//! The executive driven like the service will drive it: waypoint-reached reports, variables set
//! mid-run and every in-flight command, checking the exact waypoints that come next.

use fpma::exec::*;
use fpma::expand::Waypoint;
use fpma::expr::Value;
use fpma::geo::{distance, GeoPoint};
use fpma::model::Stage;
use fpma::parse::parse_plan;
use fpma::vehicle::VehicleParams;

/// Fixes 40-odd metres apart around the car park.
const FIXES: &str = r#"
  <fixes>
    <fix id="A" lat="41.27500" lon="1.98700" alt="0"/>
    <fix id="B" lat="41.27540" lon="1.98700" alt="0"/>
    <fix id="C" lat="41.27540" lon="1.98750" alt="0"/>
    <fix id="D" lat="41.27500" lon="1.98750" alt="0"/>
    <fix id="E" lat="41.27470" lon="1.98720" alt="0"/>
    <fix id="H" lat="41.27600" lon="1.98700" alt="0"/>
  </fixes>"#;

fn plan(vars: &str, body: &str) -> String {
    format!(
        r#"<flightPlan name="t" defaultSpeed="2"><variables>{vars}</variables>{FIXES}
  <departure><leg type="IF" fix="A"/></departure>
  <mission>{body}</mission>
  <approach><leg id="app" type="TF" fix="E"/></approach>
  <emergency name="low" on="battery &lt; 20" action="goto-stage" stage="approach"/>
</flightPlan>"#
    )
}

fn exec(vars: &str, body: &str) -> Executive {
    let p = parse_plan(&plan(vars, body), &VehicleParams::rover()).expect("test plan parses");
    Executive::new(p, VehicleParams::rover())
}

fn fix(id: &str) -> GeoPoint {
    match id {
        "A" => GeoPoint::new(41.275, 1.987),
        "B" => GeoPoint::new(41.2754, 1.987),
        "C" => GeoPoint::new(41.2754, 1.9875),
        "D" => GeoPoint::new(41.275, 1.9875),
        "E" => GeoPoint::new(41.2747, 1.9872),
        "H" => GeoPoint::new(41.276, 1.987),
        _ => unreachable!(),
    }
}

/// The fix each of the next `n` waypoints sits on ("?" when none), for compact assertions.
fn next_fixes(ex: &Executive, n: usize) -> Vec<String> {
    ex.next_waypoints(n)
        .iter()
        .map(|w| {
            ["A", "B", "C", "D", "E", "H"]
                .iter()
                .find(|f| distance(fix(f), w.pos()) < 0.01)
                .map_or_else(|| "?".to_string(), |f| f.to_string())
        })
        .collect()
}

fn legs(ws: &[Waypoint]) -> Vec<&str> {
    ws.iter().map(|w| w.leg.as_str()).collect()
}

/// Reports the next waypoint reached.
fn reach(ex: &mut Executive) -> Waypoint {
    let w = ex.next_waypoints(1).pop().expect("a waypoint to reach");
    ex.waypoint_reached(w.version, w.seq)
        .expect("report accepted");
    w
}

fn events(ex: &mut Executive) -> Vec<EventKind> {
    ex.take_events().into_iter().map(|e| e.kind).collect()
}

#[test]
fn iterative_until_is_driven_by_a_variable_set_mid_run() {
    let mut ex = exec(
        r#"<var name="done" type="bool"/>"#,
        r#"<iterative id="loop" until="done"><leg type="TF" fix="B"/><leg type="TF" fix="C"/></iterative>
           <leg type="TF" fix="D"/>"#,
    );
    assert_eq!(next_fixes(&ex, 6), ["A", "B", "C", "B", "C", "B"]);
    reach(&mut ex);
    reach(&mut ex);
    reach(&mut ex); // A, B, C: one pass done, `done` still false
    assert!(events(&mut ex).contains(&EventKind::IterationDone {
        leg: "loop".into(),
        n: 1
    }));
    assert_eq!(next_fixes(&ex, 3), ["B", "C", "B"]);
    ex.set_var("done", Value::Bool(true)).unwrap();
    // The pass under way is finished, then the loop ends.
    assert_eq!(next_fixes(&ex, 4), ["B", "C", "D", "E"]);
}

#[test]
fn while_loop_counts_with_the_iteration_builtin() {
    let ex = exec(
        "",
        r#"<iterative while="iteration &lt; 3"><leg type="TF" fix="B"/><leg type="TF" fix="C"/></iterative>"#,
    );
    assert_eq!(next_fixes(&ex, 9), ["A", "B", "C", "B", "C", "B", "C", "E"]);
}

#[test]
fn count_loops_nest() {
    let ex = exec(
        "",
        r#"<iterative count="2"><leg type="TF" fix="B"/>
             <iterative count="2"><leg type="TF" fix="C"/><leg type="TF" fix="D"/></iterative>
           </iterative>"#,
    );
    assert_eq!(
        next_fixes(&ex, 12),
        ["A", "B", "C", "D", "C", "D", "B", "C", "D", "C", "D", "E"]
    );
}

#[test]
fn alternative_is_chosen_at_activation_and_then_fixed() {
    let mut ex = exec(
        r#"<var name="go" type="bool"/>"#,
        r#"<leg type="TF" fix="B"/>
           <alternative id="alt"><when cond="go"><leg type="TF" fix="C"/></when>
             <otherwise><leg type="TF" fix="D"/></otherwise></alternative>
           <leg type="TF" fix="H"/>"#,
    );
    assert_eq!(next_fixes(&ex, 4), ["A", "B", "D", "H"]);
    reach(&mut ex);
    ex.set_var("go", Value::Bool(true)).unwrap();
    // Late change before activation: the look-ahead follows it.
    assert_eq!(next_fixes(&ex, 3), ["B", "C", "H"]);
    reach(&mut ex); // B reached: the alternative is entered now
    assert!(events(&mut ex).contains(&EventKind::BranchTaken {
        leg: "alt".into(),
        branch: 0
    }));
    ex.set_var("go", Value::Bool(false)).unwrap();
    assert_eq!(next_fixes(&ex, 2), ["C", "H"]);
}

#[test]
fn hm_hold_circles_until_its_condition_then_exits_at_the_fix() {
    let mut ex = exec(
        r#"<var name="seen" type="bool"/>"#,
        r#"<leg id="h" type="HM" fix="B" inboundCourse="0" turn="R" length="20" width="10" shape="rectangle" until="seen"/>
           <leg type="TF" fix="D"/>"#,
    );
    // A, then B (entry), then circuits of 4 corners ending at B, repeating.
    let ahead = ex.next_waypoints(11);
    assert_eq!(legs(&ahead)[1..10], ["h"; 9]);
    assert!(distance(ahead[5].pos(), fix("B")) < 0.01 && distance(ahead[9].pos(), fix("B")) < 0.01);
    for _ in 0..4 {
        reach(&mut ex);
    }
    ex.set_var("seen", Value::Bool(true)).unwrap();
    // The circuit under way ends at the fix, then the plan goes on.
    let ahead = ex.next_waypoints(4);
    assert_eq!(legs(&ahead), ["h", "h", "mission.2", "app"]);
    assert!(distance(ahead[1].pos(), fix("B")) < 0.01);
}

#[test]
fn emergency_rule_fires_on_telemetry_and_on_command() {
    let mut ex = exec(
        "",
        r#"<leg type="TF" fix="B"/><leg type="TF" fix="C"/><leg type="TF" fix="D"/>"#,
    );
    reach(&mut ex);
    reach(&mut ex);
    ex.take_events();
    ex.update_telemetry(Telemetry {
        battery: Some(15.0),
        ..Telemetry::default()
    });
    let ev = events(&mut ex);
    assert!(
        ev.contains(&EventKind::EmergencyFired { rule: "low".into() }),
        "{ev:?}"
    );
    assert!(ev.contains(&EventKind::StageChanged {
        stage: Stage::Approach
    }));
    assert_eq!(next_fixes(&ex, 2), ["E"]);
    // Edge-triggered: staying low does not fire again.
    ex.update_telemetry(Telemetry {
        battery: Some(14.0),
        ..Telemetry::default()
    });
    assert!(!events(&mut ex)
        .iter()
        .any(|e| matches!(e, EventKind::EmergencyFired { .. })));

    let mut ex = exec("", r#"<leg type="TF" fix="B"/><leg type="TF" fix="C"/>"#);
    reach(&mut ex);
    assert_eq!(
        ex.emergency(Some("nope")),
        Err(CommandError::UnknownRule("nope".into()))
    );
    ex.emergency(None).unwrap();
    assert_eq!(next_fixes(&ex, 2), ["E"]);
}

#[test]
fn skip_goto_and_stage_commands() {
    let mut ex = exec(
        "",
        r#"<leg id="b" type="TF" fix="B"/><leg id="c" type="TF" fix="C"/><leg id="d" type="TF" fix="D"/>"#,
    );
    reach(&mut ex); // A
    ex.skip_leg().unwrap(); // skips b
    assert_eq!(next_fixes(&ex, 3), ["C", "D", "E"]);
    ex.goto_leg("b").unwrap();
    assert_eq!(next_fixes(&ex, 4), ["B", "C", "D", "E"]);
    assert_eq!(
        ex.goto_leg("zz"),
        Err(CommandError::UnknownLeg("zz".into()))
    );
    ex.goto_stage(Stage::Approach).unwrap();
    assert_eq!(next_fixes(&ex, 2), ["E"]);
    assert_eq!(
        ex.goto_stage(Stage::Landing),
        Err(CommandError::EmptyStage(Stage::Landing))
    );
    ex.goto_stage(Stage::Departure).unwrap();
    assert_eq!(
        next_fixes(&ex, 2),
        ["B", "C"],
        "IF after the first waypoint adds nothing"
    );
    reach(&mut ex);
    reach(&mut ex);
    reach(&mut ex);
    reach(&mut ex);
    assert!(ex.state().completed);
    assert_eq!(ex.skip_leg(), Err(CommandError::NothingToSkip));
    assert!(events(&mut ex).contains(&EventKind::PlanCompleted));
}

#[test]
fn goto_into_a_loop_and_a_branch() {
    let mut ex = exec(
        "",
        r#"<iterative id="l" count="2"><leg type="TF" fix="B"/><leg id="lc" type="TF" fix="C"/></iterative>
           <alternative id="a"><when cond="false"><leg id="deep" type="TF" fix="H"/></when></alternative>"#,
    );
    ex.goto_leg("lc").unwrap();
    assert_eq!(next_fixes(&ex, 4), ["C", "B", "C", "E"]);
    ex.goto_leg("deep").unwrap();
    assert_eq!(next_fixes(&ex, 2), ["H", "E"]);
    assert!(events(&mut ex).contains(&EventKind::BranchTaken {
        leg: "a".into(),
        branch: 0
    }));
}

#[test]
fn set_var_is_validated() {
    let mut ex = exec(
        r#"<var name="go" type="bool"/>"#,
        r#"<leg type="TF" fix="B"/>"#,
    );
    assert_eq!(
        ex.set_var("nope", Value::Bool(true)),
        Err(CommandError::UnknownVariable("nope".into()))
    );
    assert!(matches!(
        ex.set_var("go", Value::Number(1.0)),
        Err(CommandError::TypeMismatch { .. })
    ));
    assert!(ex.set_var("iteration", Value::Number(1.0)).is_err());
    ex.set_var("go", Value::Bool(true)).unwrap();
    assert_eq!(ex.state().vars["go"], Value::Bool(true));
}

#[test]
fn replace_is_atomic_and_versioned() {
    let mut ex = exec("", r#"<leg type="TF" fix="B"/><leg type="TF" fix="C"/>"#);
    reach(&mut ex);
    let old = ex.next_waypoints(2);
    assert!(old.iter().all(|w| w.version == 1));
    // An invalid replacement changes nothing.
    let mut bad = parse_plan(
        &plan("", r#"<leg type="TF" fix="B"/>"#),
        &VehicleParams::rover(),
    )
    .unwrap();
    let aircraft_scan = parse_plan(
        &plan(
            "",
            r#"<scan spacing="10"><pt lat="41.275" lon="1.987"/><pt lat="41.276" lon="1.987"/><pt lat="41.276" lon="1.988"/></scan>"#,
        ),
        &VehicleParams::rover(),
    )
    .unwrap();
    bad.mission = aircraft_scan.mission.clone();
    let mut strict = Executive::new(
        parse_plan(
            &plan("", r#"<leg type="TF" fix="B"/>"#),
            &VehicleParams::aircraft(),
        )
        .unwrap(),
        VehicleParams::aircraft(),
    );
    assert!(matches!(
        strict.replace_plan(bad),
        Err(CommandError::InvalidPlan(_))
    ));
    assert_eq!(strict.version(), 1);

    let new = parse_plan(
        &plan("", r#"<leg type="TF" fix="D"/><leg type="TF" fix="H"/>"#),
        &VehicleParams::rover(),
    )
    .unwrap();
    assert_eq!(ex.replace_plan(new), Ok(2));
    let ahead = ex.next_waypoints(10);
    assert!(
        ahead.iter().all(|w| w.version == 2),
        "only the new plan is handed out"
    );
    // The new plan's IF adds nothing: the vehicle is already flying.
    assert_eq!(next_fixes(&ex, 10), ["D", "H", "E"]);
    // The vehicle reporting a waypoint of the old plan is refused, and changes nothing.
    assert_eq!(
        ex.waypoint_reached(1, old[0].seq),
        Err(CommandError::StaleVersion { got: 1, current: 2 })
    );
    assert_eq!(ex.state().version, 2);
    let ev = ex.take_events();
    assert!(ev
        .iter()
        .any(|e| e.kind == EventKind::PlanReplaced && e.version == 2));
    // Reports must follow the stream.
    let w = reach(&mut ex);
    assert_eq!(
        ex.waypoint_reached(2, w.seq),
        Err(CommandError::AlreadyReached {
            seq: w.seq,
            next: w.seq + 1
        })
    );
    assert_eq!(
        ex.waypoint_reached(2, w.seq + 100),
        Err(CommandError::BeyondPlan(w.seq + 100))
    );
}

const SCAN: &str = r#"<scan id="s" spacing="6" sweepAngle="90" entry="left" startSide="back">
    <pt lat="41.27540" lon="1.98700"/><pt lat="41.27570" lon="1.98700"/>
    <pt lat="41.27570" lon="1.98760"/><pt lat="41.27540" lon="1.98760"/></scan>"#;

#[test]
fn modify_a_scan_spacing_in_flight() {
    let mut ex = exec(
        "",
        &format!(r#"<leg type="TF" fix="B"/>{SCAN}<leg type="TF" fix="D"/>"#),
    );
    reach(&mut ex);
    let before: Vec<Waypoint> = ex
        .next_waypoints(100)
        .into_iter()
        .filter(|w| w.leg == "s")
        .collect();
    assert_eq!(before.len(), 2 * 6, "33 m across at 6 m: 6 tracks");
    assert_eq!(
        ex.modify_leg("s", &[("spacing".into(), "12".into())]),
        Ok(2)
    );
    let after: Vec<Waypoint> = ex
        .next_waypoints(100)
        .into_iter()
        .filter(|w| w.leg == "s")
        .collect();
    assert_eq!(after.len(), 2 * 3, "33 m across at 12 m: 3 tracks");
    assert!(after.iter().all(|w| w.version == 2));
    // Invalid changes are refused with the reason and change nothing.
    let e = ex
        .modify_leg("s", &[("spacing".into(), "2".into())])
        .unwrap_err();
    assert!(e.to_string().contains("minimum waypoint distance"), "{e}");
    assert!(ex
        .modify_leg("s", &[("spacing".into(), "wide".into())])
        .is_err());
    assert_eq!(ex.version(), 2);
    // Modifying the scan while it is flown restarts it with the new spacing from where we are.
    reach(&mut ex);
    reach(&mut ex);
    assert_eq!(ex.state().leg.as_deref(), Some("s"));
    ex.modify_leg("s", &[("spacing".into(), "16".into())])
        .unwrap();
    let now: Vec<Waypoint> = ex
        .next_waypoints(100)
        .into_iter()
        .filter(|w| w.leg == "s")
        .collect();
    assert_eq!(
        now.len(),
        2 * 3 - 1,
        "3 tracks; the first point is within 4.5 m of where the vehicle is, so dropped"
    );
}

#[test]
fn hold_here_then_exit_resumes_the_interrupted_leg() {
    let mut ex = exec("", r#"<leg type="TF" fix="B"/><leg type="TF" fix="C"/>"#);
    reach(&mut ex); // at A, heading to B (north)
    ex.hold_here(&HoldHere {
        length: Some(20.0),
        width: Some(10.0),
        ..HoldHere::default()
    })
    .unwrap();
    assert!(ex.state().holding);
    let ahead = ex.next_waypoints(8);
    // A rover's hold is a rectangle east of the inbound (north) course: 4 corners back to A.
    let a = fix("A");
    let expect = [(10.0, 0.0), (10.0, -20.0), (0.0, -20.0), (0.0, 0.0)];
    let f = fpma::geo::LocalFrame::new(a);
    for (w, (e, n)) in ahead.iter().zip(expect.iter().cycle()) {
        let p = f.to_local(w.pos());
        assert!((p.e - e).abs() < 0.01 && (p.n - n).abs() < 0.01, "{p:?}");
        assert!(w.waits);
    }
    reach(&mut ex);
    ex.exit_hold(false).unwrap();
    // The circuit finishes at the fix, then B, C as before.
    assert_eq!(next_fixes(&ex, 5), ["?", "?", "A", "B", "C"]);
    ex.exit_hold(true).unwrap();
    assert_eq!(next_fixes(&ex, 2), ["B", "C"]);
    assert_eq!(ex.exit_hold(false), Err(CommandError::NotHolding));
}

#[test]
fn pause_and_resume() {
    let mut ex = exec("", r#"<leg type="TF" fix="B"/>"#);
    reach(&mut ex);
    ex.pause().unwrap();
    assert!(ex.next_waypoints(3).is_empty());
    assert_eq!(ex.pause(), Err(CommandError::AlreadyPaused));
    ex.resume().unwrap();
    assert_eq!(ex.resume(), Err(CommandError::NotPaused));
    assert_eq!(next_fixes(&ex, 3), ["B", "E"]);
}

#[test]
fn retask_visits_points_in_nearest_neighbour_order() {
    let pois = [fix("H"), fix("C"), fix("B")];
    let mut ex = exec("", r#"<leg type="TF" fix="D"/><leg type="TF" fix="E"/>"#);
    reach(&mut ex); // at A
    ex.retask(&pois, None, RetaskMode::Now).unwrap();
    // From A: B (44 m), then C, then H; then the interrupted leg to D resumes.
    assert_eq!(next_fixes(&ex, 5), ["B", "C", "H", "D", "E"]);
    assert_eq!(ex.version(), 1, "an interruption does not change the plan");

    let mut ex = exec("", r#"<leg type="TF" fix="D"/><leg type="TF" fix="E"/>"#);
    reach(&mut ex);
    assert_eq!(ex.retask(&pois, None, RetaskMode::AfterCurrentLeg), Ok(2));
    // Ordered from D, where the current leg ends: C, B, H.
    assert_eq!(next_fixes(&ex, 6), ["D", "C", "B", "H", "E"]);
    assert_eq!(
        ex.retask(&[], None, RetaskMode::Now),
        Err(CommandError::NoPoints)
    );
    let fresh = exec("", r#"<leg type="TF" fix="D"/>"#);
    let mut fresh2 = fresh.clone();
    assert!(
        fresh2.hold_here(&HoldHere::default()).is_err(),
        "no position before the first waypoint"
    );
}

#[test]
fn progress_by_distance_increases_to_one() {
    let mut ex = exec(
        "",
        r#"<leg type="TF" fix="B"/><leg type="TF" fix="C"/><leg type="TF" fix="D"/>"#,
    );
    let mut last = -1.0;
    while !ex.state().completed {
        reach(&mut ex);
        let p = ex
            .take_events()
            .into_iter()
            .filter_map(|e| match e.kind {
                EventKind::Progress { fraction, .. } => Some(fraction),
                _ => None,
            })
            .next_back()
            .unwrap();
        assert!(p > last, "{p} after {last}");
        last = p;
    }
    assert_eq!(last, 1.0);
    // A-B is 44.4 m of 44.4 + 41.9 + 44.4 + 34.3 (to E): check the first step's weight.
    let mut ex = exec(
        "",
        r#"<leg type="TF" fix="B"/><leg type="TF" fix="C"/><leg type="TF" fix="D"/>"#,
    );
    reach(&mut ex);
    reach(&mut ex);
    let total: f64 = [("A", "B"), ("B", "C"), ("C", "D"), ("D", "E")]
        .iter()
        .map(|(a, b)| distance(fix(a), fix(b)))
        .sum();
    assert!((ex.progress() - distance(fix("A"), fix("B")) / total).abs() < 1e-9);
}

#[test]
fn events_tell_the_story() {
    let mut ex = exec(
        "",
        r#"<iterative id="l" count="1"><leg id="b" type="TF" fix="B"/></iterative>"#,
    );
    reach(&mut ex);
    reach(&mut ex);
    let ev = events(&mut ex);
    let want = [
        EventKind::StageChanged {
            stage: Stage::Departure,
        },
        EventKind::LegStarted {
            leg: "departure.1".into(),
        },
        EventKind::WaypointReached {
            seq: 0,
            leg: "departure.1".into(),
        },
        EventKind::LegCompleted {
            leg: "departure.1".into(),
            skipped: false,
        },
        EventKind::StageChanged {
            stage: Stage::Mission,
        },
        EventKind::LegStarted { leg: "b".into() },
    ];
    assert_eq!(ev[..want.len()], want);
    assert!(ev.contains(&EventKind::IterationDone {
        leg: "l".into(),
        n: 1
    }));
    assert!(ev.contains(&EventKind::StageChanged {
        stage: Stage::Approach
    }));
}

#[test]
fn example_plans_parse_and_expand() {
    let root = concat!(env!("CARGO_MANIFEST_DIR"), "/../../config/flightplans/");
    for (file, vehicle) in [
        ("rover-carpark.xml", VehicleParams::rover()),
        ("aircraft-demo.xml", VehicleParams::aircraft()),
    ] {
        let src = std::fs::read_to_string(format!("{root}{file}")).unwrap();
        let p = parse_plan(&src, &vehicle).unwrap_or_else(|e| panic!("{file}:{e}"));
        let ws = expand_nominal(p, vehicle.clone()).unwrap();
        assert!(ws.len() > 20, "{file}: {}", ws.len());
        assert!(ws.iter().any(|w| w.waits), "{file} has a waiting hold");
        for pair in ws.windows(2) {
            if pair[1].tag == fpma::expand::WaypointTag::Nav {
                let d = distance(pair[0].pos(), pair[1].pos());
                assert!(
                    d >= vehicle.min_wp_distance - 1e-6,
                    "{file}: waypoints {d} m apart"
                );
            }
        }
    }
}
