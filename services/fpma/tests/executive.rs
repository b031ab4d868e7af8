//! The executive driven like the service will drive it: waypoint-reached reports, variables set
//! mid-run and every in-flight command, checking the exact waypoints that come next.

use fpma::exec::*;
use fpma::expand::{enforce_min_distance, expand_scan, Ctx, Origin, Waypoint};
use fpma::expr::Value;
use fpma::geo::{distance, GeoPoint};
use fpma::model::{NodeKind, Stage};
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

/// Local east/north of a waypoint around fix `f`, rounded to centimetres for exact comparison.
fn enu(f: &str, w: &Waypoint) -> (f64, f64) {
    let p = fpma::geo::LocalFrame::new(fix(f)).to_local(w.pos());
    ((p.e * 100.0).round() / 100.0, (p.n * 100.0).round() / 100.0)
}

/// A 20 m × 10 m rectangle hold at B, inbound north, turning right: its corners around B.
const RECT: [(f64, f64); 4] = [(10.0, 0.0), (10.0, -20.0), (0.0, -20.0), (0.0, 0.0)];

#[test]
fn hf_hold_flies_its_circuit_count_then_exits() {
    let ex = exec(
        "",
        r#"<leg id="h" type="HF" fix="B" inboundCourse="0" turn="R" length="20" width="10" shape="rectangle" circuits="2"/>
           <leg type="TF" fix="D"/>"#,
    );
    let ahead = ex.next_waypoints(20);
    // A, the entry at B, two circuits of four corners, then D and the approach.
    assert_eq!(
        legs(&ahead),
        [&["departure.1"][..], &["h"; 9], &["mission.2", "app"]].concat()
    );
    let hold: Vec<(f64, f64)> = ahead[1..10].iter().map(|w| enu("B", w)).collect();
    let want: Vec<(f64, f64)> = [&[(0.0, 0.0)][..], &RECT, &RECT].concat();
    assert_eq!(hold, want);
    assert!(ahead[1..10].iter().all(|w| w.fly_over && !w.waits));
    // Without a count an HF flies one circuit.
    let one = exec(
        "",
        r#"<leg id="h" type="HF" fix="B" inboundCourse="0" turn="L" length="20" width="10" shape="rectangle"/>"#,
    );
    let ahead = one.next_waypoints(10);
    assert_eq!(
        legs(&ahead),
        [&["departure.1"][..], &["h"; 5], &["app"]].concat()
    );
    // Turning left mirrors the rectangle to the west of the inbound course.
    let left: Vec<(f64, f64)> = ahead[2..6].iter().map(|w| enu("B", w)).collect();
    assert_eq!(
        left,
        [(-10.0, 0.0), (-10.0, -20.0), (0.0, -20.0), (0.0, 0.0)]
    );
}

#[test]
fn hm_hold_with_a_circuit_count_exits_at_the_count_or_its_condition() {
    let body = r#"<leg id="h" type="HM" fix="B" inboundCourse="0" turn="R" length="20" width="10" shape="rectangle" circuits="3" until="seen"/>
           <leg type="TF" fix="D"/>"#;
    let vars = r#"<var name="seen" type="bool"/>"#;
    let ex = exec(vars, body);
    let ahead = ex.next_waypoints(20);
    // A bound, not a wait: the entry, three circuits, then on.
    assert_eq!(
        legs(&ahead),
        [&["departure.1"][..], &["h"; 13], &["mission.2", "app"]].concat()
    );
    assert!(ahead.iter().all(|w| !w.waits));
    let mut ex = exec(vars, body);
    for _ in 0..3 {
        reach(&mut ex); // A, the entry at B, the first corner
    }
    ex.set_var("seen", Value::Bool(true)).unwrap();
    let ahead = ex.next_waypoints(5);
    assert_eq!(legs(&ahead), ["h", "h", "h", "mission.2", "app"]);
    assert_eq!(enu("B", &ahead[2]), (0.0, 0.0), "exits at the fix");
}

#[test]
fn ha_hold_circles_until_telemetry_reports_its_altitude() {
    let mut ex = exec(
        "",
        r#"<leg id="h" type="HA" fix="B" inboundCourse="0" turn="R" length="20" width="10" shape="rectangle" targetAlt="30" altTolerance="2"/>
           <leg type="TF" fix="D"/>"#,
    );
    // Nominally (no telemetry yet) one circuit at the target altitude, marked as waiting.
    let nominal = expand_nominal(ex.plan().clone(), VehicleParams::rover()).unwrap();
    assert_eq!(
        legs(&nominal),
        [&["departure.1"][..], &["h"; 5], &["mission.2", "app"]].concat()
    );
    assert!(nominal[1..6].iter().all(|w| w.waits && w.alt == 30.0));
    reach(&mut ex); // A
    ex.update_telemetry(Telemetry {
        alt: Some(12.0),
        ..Telemetry::default()
    });
    for _ in 0..5 {
        reach(&mut ex); // the entry and one circuit: still climbing
    }
    assert_eq!(ex.state().leg.as_deref(), Some("h"));
    let ahead = ex.next_waypoints(6);
    assert_eq!(legs(&ahead), ["h"; 6], "another circuit, and another");
    let corners: Vec<(f64, f64)> = ahead[..4].iter().map(|w| enu("B", w)).collect();
    assert_eq!(corners, RECT);
    ex.update_telemetry(Telemetry {
        alt: Some(29.0),
        ..Telemetry::default()
    });
    // Within the tolerance: the circuit under way ends at the fix, then the plan goes on.
    let ahead = ex.next_waypoints(6);
    assert_eq!(legs(&ahead), ["h", "h", "h", "h", "mission.2", "app"]);
    assert_eq!(enu("B", &ahead[3]), (0.0, 0.0));
}

#[test]
fn modified_scan_hands_out_exactly_the_new_geometry() {
    let mut ex = exec(
        "",
        &format!(r#"<leg type="TF" fix="B"/>{SCAN}<leg type="TF" fix="D"/>"#),
    );
    reach(&mut ex); // A; next is B, then the scan
    ex.modify_leg("s", &[("spacing".into(), "12".into())])
        .unwrap();
    // What the same plan written with spacing 12 expands to, point for point.
    let written = parse_plan(
        &plan(
            "",
            &format!(
                r#"<leg type="TF" fix="B"/>{}<leg type="TF" fix="D"/>"#,
                SCAN.replace(r#"spacing="6""#, r#"spacing="12""#)
            ),
        ),
        &VehicleParams::rover(),
    )
    .unwrap();
    let want = expand_nominal(written, VehicleParams::rover()).unwrap();
    let got = ex.next_waypoints(100);
    assert_eq!(got.len(), want.len() - 1, "all but A, already reached");
    for (g, w) in got.iter().zip(&want[1..]) {
        assert!(distance(g.pos(), w.pos()) < 0.001, "{g:?} vs {w:?}");
        assert_eq!((g.leg.as_str(), g.fly_over), (w.leg.as_str(), w.fly_over));
    }
    // Mid-scan: the new tracks start from where the vehicle is.
    reach(&mut ex); // B
    reach(&mut ex); // the scan's first point
    let here = ex.next_waypoints(0);
    assert!(here.is_empty());
    ex.modify_leg("s", &[("spacing".into(), "16".into())])
        .unwrap();
    let got: Vec<Waypoint> = ex
        .next_waypoints(100)
        .into_iter()
        .filter(|w| w.leg == "s")
        .collect();
    let NodeKind::Scan(scan) = &ex.plan().find("s").unwrap().kind else {
        panic!("s is a scan")
    };
    let prev = want[2].pos(); // the scan's first point, where the vehicle is
    let v = VehicleParams::rover();
    let ctx = Ctx {
        vehicle: &v,
        prev: Some(Origin {
            pos: prev,
            alt: 0.0,
            speed: 2.0,
        }),
        plan_speed: Some(2.0),
    };
    let fresh = enforce_min_distance(Some(prev), expand_scan(scan, "s", &ctx), v.min_wp_distance);
    assert_eq!(got.len(), fresh.len());
    for (g, w) in got.iter().zip(&fresh) {
        assert!(distance(g.pos(), w.pos()) < 0.001, "{g:?} vs {w:?}");
    }
}

#[test]
fn insert_legs_flies_them_after_the_current_leg() {
    let mut ex = exec(
        "",
        r#"<leg id="b" type="TF" fix="B"/><leg id="d" type="TF" fix="D"/>"#,
    );
    reach(&mut ex); // A; flying b
    let v = ex
        .insert_legs(r#"<leg type="TF" fix="H"/><leg id="c" type="TF" fix="C" flyOver="true"/>"#)
        .unwrap();
    assert_eq!(v, 2);
    assert_eq!(next_fixes(&ex, 6), ["B", "H", "C", "D", "E"]);
    let ahead = ex.next_waypoints(3);
    assert_eq!(legs(&ahead), ["b", "insert.v2.1", "c"]);
    assert!(ahead.iter().all(|w| w.version == 2));
    assert!(events(&mut ex).contains(&EventKind::PlanModified {
        leg: "insert.v2.1".into()
    }));
    // Refusals name the fragment's line and change nothing.
    let e = ex
        .insert_legs("<leg type=\"TF\" fix=\"B\"/>\n<leg type=\"TF\" fix=\"Q\"/>")
        .unwrap_err();
    assert!(
        e.to_string().contains("2:") && e.to_string().contains("unknown fix `Q`"),
        "{e}"
    );
    let e = ex
        .insert_legs(r#"<leg id="d" type="TF" fix="B"/>"#)
        .unwrap_err();
    assert!(e.to_string().contains("`d` is used twice"), "{e}");
    assert!(ex.insert_legs("").is_err());
    assert_eq!(ex.version(), 2);
    assert_eq!(next_fixes(&ex, 6), ["B", "H", "C", "D", "E"]);
}

#[test]
fn out_of_range_arguments_are_refused_and_change_nothing() {
    let mut ex = exec(
        r#"<var name="n" type="number"/>"#,
        r#"<leg type="TF" fix="B"/><leg type="TF" fix="C"/>"#,
    );
    reach(&mut ex);
    let before = ex.next_waypoints(5);
    for h in [
        HoldHere {
            length: Some(f64::NAN),
            ..HoldHere::default()
        },
        HoldHere {
            length: Some(-20.0),
            ..HoldHere::default()
        },
        HoldHere {
            width: Some(1.0),
            ..HoldHere::default()
        },
        HoldHere {
            inbound_course: Some(f64::INFINITY),
            ..HoldHere::default()
        },
    ] {
        let e = ex.hold_here(&h).unwrap_err();
        assert!(matches!(e, CommandError::BadArgument { .. }), "{e}");
    }
    let e = ex
        .retask(&[GeoPoint::new(91.0, 2.0)], None, RetaskMode::Now)
        .unwrap_err();
    assert!(e.to_string().contains("latitude 91"), "{e}");
    assert!(ex
        .retask(&[GeoPoint::new(41.0, f64::NAN)], None, RetaskMode::Now)
        .is_err());
    assert!(ex
        .retask(&[fix("H")], Some(f64::NAN), RetaskMode::AfterCurrentLeg)
        .is_err());
    assert!(ex.set_var("n", Value::Number(f64::INFINITY)).is_err());
    // Telemetry that is not a number is ignored.
    ex.update_telemetry(Telemetry {
        position: Some(GeoPoint::new(f64::NAN, 0.0)),
        alt: Some(f64::NAN),
        battery: Some(f64::NAN),
        ..Telemetry::default()
    });
    assert_eq!(ex.next_waypoints(5), before);
    assert_eq!(ex.version(), 1);
    assert!(!ex.state().holding);
}

/// One in-flight input, with arguments that may be nonsense.
#[derive(Clone, Debug)]
enum Input {
    Reach(u8),
    Skip,
    Goto(u8),
    Stage(u8),
    SetVar(u8, f64),
    HoldHere(f64, f64, f64),
    ExitHold(bool),
    Pause,
    Resume,
    Modify(u8, u8, f64),
    Retask(f64, f64, bool),
    Insert(u8),
    Emergency(bool),
    Telemetry(f64, f64, f64),
    Replace,
}

fn any_f64() -> impl Strategy<Value = f64> {
    prop_oneof![
        -200.0..200.0f64,
        Just(f64::NAN),
        Just(f64::INFINITY),
        Just(0.0),
        Just(1e300)
    ]
}

fn input() -> impl Strategy<Value = Input> {
    prop_oneof![
        4 => (0u8..4).prop_map(Input::Reach),
        1 => any::<u8>().prop_map(|_| Input::Skip),
        1 => any::<u8>().prop_map(Input::Goto),
        1 => any::<u8>().prop_map(Input::Stage),
        1 => (any::<u8>(), any_f64()).prop_map(|(k, v)| Input::SetVar(k, v)),
        1 => (any_f64(), any_f64(), any_f64()).prop_map(|(a, b, c)| Input::HoldHere(a, b, c)),
        1 => any::<bool>().prop_map(Input::ExitHold),
        1 => Just(Input::Pause),
        1 => Just(Input::Resume),
        1 => (any::<u8>(), any::<u8>(), any_f64()).prop_map(|(a, b, v)| Input::Modify(a, b, v)),
        1 => (any_f64(), any_f64(), any::<bool>()).prop_map(|(a, b, c)| Input::Retask(a, b, c)),
        1 => any::<u8>().prop_map(Input::Insert),
        1 => any::<bool>().prop_map(Input::Emergency),
        1 => (any_f64(), any_f64(), any_f64()).prop_map(|(a, b, c)| Input::Telemetry(a, b, c)),
        1 => Just(Input::Replace),
    ]
}

use proptest::prelude::*;

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    /// Whatever a station sends, in whatever order, the executive answers (accepts or refuses)
    /// and never panics; what it hands out is always a finite position.
    #[test]
    fn the_executive_never_panics_on_commands(inputs in proptest::collection::vec(input(), 1..40)) {
        let root = concat!(env!("CARGO_MANIFEST_DIR"), "/../../config/flightplans/");
        let src = std::fs::read_to_string(format!("{root}rover-carpark.xml")).unwrap();
        let plan = parse_plan(&src, &VehicleParams::rover()).unwrap();
        let ids: Vec<String> = ["hold", "area", "laps", "laps.1", "check", "wait", "departure.2", "nope"]
            .iter().map(|s| s.to_string()).collect();
        let attrs = ["spacing", "length", "width", "speed", "alt", "sweepAngle", "fix", "type"];
        let vars = ["inspect", "laps", "battery", "alt", "iteration", "ghost"];
        let mut ex = Executive::new(plan.clone(), VehicleParams::rover());
        for i in inputs {
            let _ = match i {
                Input::Reach(k) => {
                    let next = ex.next_waypoints(usize::from(k) + 1);
                    match next.last() {
                        Some(w) => ex.waypoint_reached(w.version, w.seq),
                        None => ex.waypoint_reached(ex.version(), u64::from(k)),
                    }
                }
                Input::Skip => ex.skip_leg(),
                Input::Goto(k) => ex.goto_leg(&ids[usize::from(k) % ids.len()]),
                Input::Stage(k) => ex.goto_stage(Stage::ALL[usize::from(k) % 5]),
                Input::SetVar(k, v) => {
                    let name = vars[usize::from(k) % vars.len()];
                    let value = if name == "inspect" { Value::Bool(v > 0.0) } else { Value::Number(v) };
                    ex.set_var(name, value)
                }
                Input::HoldHere(l, w, c) => ex.hold_here(&HoldHere {
                    length: Some(l), width: Some(w), inbound_course: Some(c), ..HoldHere::default()
                }),
                Input::ExitHold(now) => ex.exit_hold(now),
                Input::Pause => ex.pause(),
                Input::Resume => ex.resume(),
                Input::Modify(a, b, v) => ex
                    .modify_leg(&ids[usize::from(a) % ids.len()], &[(attrs[usize::from(b) % attrs.len()].into(), v.to_string())])
                    .map(drop),
                Input::Retask(a, b, now) => {
                    let p = GeoPoint::new(41.275 + a / 1e4, 1.987 + b / 1e4);
                    let mode = if now { RetaskMode::Now } else { RetaskMode::AfterCurrentLeg };
                    ex.retask(&[p, fix("H")], None, mode).map(drop)
                }
                Input::Insert(k) => ex
                    .insert_legs(["<leg type=\"TF\" fix=\"P2\"/>", "<leg type=\"TF\" fix=\"X\"/>", "<leg", ""][usize::from(k) % 4])
                    .map(drop),
                Input::Emergency(named) => ex.emergency(named.then_some("low-battery")),
                Input::Telemetry(a, b, c) => {
                    ex.update_telemetry(Telemetry {
                        position: Some(GeoPoint::new(41.275 + a / 1e4, 1.987 + b / 1e4)),
                        alt: Some(c),
                        battery: Some(c),
                        ..Telemetry::default()
                    });
                    Ok(())
                }
                Input::Replace => ex.replace_plan(plan.clone()).map(drop),
            };
            for w in ex.next_waypoints(8) {
                prop_assert!(w.lat.is_finite() && w.lon.is_finite() && w.alt.is_finite() && w.speed.is_finite(), "{w:?}");
            }
            let p = ex.progress();
            prop_assert!((0.0..=1.0).contains(&p), "progress {p}");
            ex.take_events();
        }
    }
}

#[test]
fn changes_that_would_never_end_are_refused() {
    let body = r#"<leg id="h" type="HF" fix="B" inboundCourse="0" turn="R" length="20" width="10" shape="rectangle"/>
                  <leg type="TF" fix="D"/>"#;
    let mut ex = exec("", body);
    reach(&mut ex);
    let before = ex.next_waypoints(8);
    // Four billion circuits: the plan would not end within the million-waypoint limit.
    let e = ex
        .modify_leg("h", &[("circuits".into(), "4000000000".into())])
        .unwrap_err();
    assert!(
        matches!(e, CommandError::Endless(ExpandError::Endless(_))),
        "{e}"
    );
    assert!(e.to_string().contains("without ending"), "{e}");
    let e = ex
        .insert_legs(r#"<iterative count="4000000000"><leg type="TF" fix="C"/><leg type="TF" fix="H"/></iterative>"#)
        .unwrap_err();
    assert!(e.to_string().contains("without ending"), "{e}");
    assert_eq!(ex.version(), 1);
    assert_eq!(ex.next_waypoints(8), before);
}

#[test]
fn nominal_expansion_shows_a_waiting_loop_once_marked() {
    let ex = exec(
        r#"<var name="done" type="bool"/>"#,
        r#"<iterative id="l" until="done"><leg type="TF" fix="B"/><leg type="TF" fix="C"/></iterative>
           <iterative id="n" while="iteration &lt; 2"><leg type="TF" fix="D"/><leg type="TF" fix="H"/></iterative>"#,
    );
    let ws = expand_nominal(ex.plan().clone(), VehicleParams::rover()).unwrap();
    let at: Vec<(String, bool)> = ws
        .iter()
        .map(|w| {
            let f = ["A", "B", "C", "D", "E", "H"]
                .into_iter()
                .find(|f| distance(fix(f), w.pos()) < 0.01)
                .unwrap_or("?");
            (f.to_string(), w.waits)
        })
        .collect();
    let want: Vec<(String, bool)> = [
        ("A", false),
        ("B", true),
        ("C", true),
        ("D", false),
        ("H", false),
        ("D", false),
        ("H", false),
        ("E", false),
    ]
    .iter()
    .map(|(f, w)| (f.to_string(), *w))
    .collect();
    // The `until done` loop waits for a variable: one pass, marked. The `while iteration < 2`
    // loop ends by itself: both passes, unmarked.
    assert_eq!(at, want);
}
