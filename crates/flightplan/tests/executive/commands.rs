//! The in-flight commands: skip, go to, set a variable, replace, modify, pause, re-task, insert;
//! arguments out of range and changes that would never end are refused and change nothing.

use super::*;

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
    let mut bad = parse_plan(&plan("", r#"<leg type="TF" fix="B"/>"#)).unwrap();
    let aircraft_scan = parse_plan(&plan(
        "",
        r#"<scan spacing="10"><pt lat="41.275" lon="1.987"/><pt lat="41.276" lon="1.987"/><pt lat="41.276" lon="1.988"/></scan>"#,
    ))
    .unwrap();
    bad.mission = aircraft_scan.mission.clone();
    // Checked for a rover, whose turns fit 10 m tracks; not for the aircraft flying `strict`.
    let bad = check::check(bad, &VehicleParams::rover()).unwrap();
    let mut strict = Executive::from_checked(
        check::load(
            &plan("", r#"<leg type="TF" fix="B"/>"#),
            &VehicleParams::aircraft(),
        )
        .unwrap(),
    );
    assert!(matches!(
        strict.replace_plan(bad),
        Err(CommandError::InvalidPlan(_))
    ));
    assert_eq!(strict.version(), 1);

    let new = check::load(
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
fn modified_scan_hands_out_exactly_the_new_geometry() {
    let mut ex = exec(
        "",
        &format!(r#"<leg type="TF" fix="B"/>{SCAN}<leg type="TF" fix="D"/>"#),
    );
    reach(&mut ex); // A; next is B, then the scan
    ex.modify_leg("s", &[("spacing".into(), "12".into())])
        .unwrap();
    // What the same plan written with spacing 12 expands to, point for point.
    let written = parse_plan(&plan(
        "",
        &format!(
            r#"<leg type="TF" fix="B"/>{}<leg type="TF" fix="D"/>"#,
            SCAN.replace(r#"spacing="6""#, r#"spacing="12""#)
        ),
    ))
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
