//! Holds: plan holds ended by circuits, conditions or altitude, and the hold commanded in flight.

use super::*;

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
    let f = flightplan::geo::LocalFrame::new(a);
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

/// Local east/north of a waypoint around fix `f`, rounded to centimetres for exact comparison.
fn enu(f: &str, w: &Waypoint) -> (f64, f64) {
    let p = flightplan::geo::LocalFrame::new(fix(f)).to_local(w.pos());
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
