//! How the executive walks a plan: loops, alternatives, emergency rules, progress and events,
//! the example plans, the nominal expansion.

use super::*;

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
        let p = check::load(&src, &vehicle).unwrap_or_else(|e| panic!("{file}:{e}"));
        let ws = p.nominal();
        assert!(ws.len() > 20, "{file}: {}", ws.len());
        assert!(ws.iter().any(|w| w.waits), "{file} has a waiting hold");
        for pair in ws.windows(2) {
            if pair[1].tag == flightplan::expand::WaypointTag::Nav {
                let d = distance(pair[0].pos(), pair[1].pos());
                assert!(
                    d >= vehicle.min_wp_distance - 1e-6,
                    "{file}: waypoints {d} m apart"
                );
            }
        }
    }
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

#[test]
fn the_distance_left_for_the_eta_covers_the_plan_and_the_target_leg() {
    let mut ex = exec(
        "",
        r#"<leg id="b" type="TF" fix="B"/><leg id="c" type="TF" fix="C"/>"#,
    );
    let (ab, bc, ce) = (
        distance(fix("A"), fix("B")),
        distance(fix("B"), fix("C")),
        distance(fix("C"), fix("E")),
    );
    reach(&mut ex); // A: heading for B
    let (plan_m, leg_m) = ex.remaining_m();
    assert!((plan_m - (ab + bc + ce)).abs() < 0.5, "{plan_m}");
    assert!((leg_m - ab).abs() < 0.5, "{leg_m}");
    // Half way to B, by telemetry: half of that leg is left.
    let half = GeoPoint::new(41.2752, 1.987);
    ex.update_telemetry(Telemetry {
        position: Some(half),
        ..Telemetry::default()
    });
    let (plan_m, leg_m) = ex.remaining_m();
    assert!((leg_m - ab / 2.0).abs() < 0.5, "{leg_m}");
    assert!((plan_m - (ab / 2.0 + bc + ce)).abs() < 0.5, "{plan_m}");
    reach(&mut ex); // B: heading for C
    assert!((ex.remaining_m().1 - bc).abs() < 0.5);
}

/// The first waypoint of a plan's landing sequence is marked for the autopilot's
/// DO_LAND_START: the approach's first in a plan with an approach, the landing in one without,
/// none in a plan that does not land; also when a command jumps to the approach.
#[test]
fn the_landing_sequence_is_marked_where_it_begins() {
    let root = concat!(env!("CARGO_MANIFEST_DIR"), "/../../config/flightplans/");
    let marked = |ws: &[Waypoint]| -> Vec<String> {
        ws.iter()
            .filter(|w| w.land_start)
            .map(|w| w.leg.clone())
            .collect()
    };
    let src = std::fs::read_to_string(format!("{root}plane-circuit.xml")).unwrap();
    let p = check::load(&src, &VehicleParams::aircraft()).unwrap();
    assert_eq!(marked(p.nominal()), ["final"]);
    let mut ex = Executive::from_checked(p);
    ex.goto_stage(Stage::Approach).unwrap();
    let next = ex.next_waypoints(3);
    assert_eq!(marked(&next), ["final"]);
    assert!(next[0].land_start, "the approach begins at once");

    let no_approach = src.replace(
        r#"<approach>
    <leg id="final" type="TF" fix="FAF" flyOver="true"/>
  </approach>"#,
        "",
    );
    assert_ne!(no_approach, src);
    let p = check::load(&no_approach, &VehicleParams::aircraft()).unwrap();
    let ws = p.nominal();
    let at: Vec<_> = ws.iter().filter(|w| w.land_start).collect();
    assert_eq!(at.len(), 1, "{ws:?}");
    assert_eq!(at[0].tag, flightplan::expand::WaypointTag::Land);

    // A plan without a landing has no landing sequence, its approach included.
    assert!(marked(&exec("", r#"<leg type="TF" fix="B"/>"#).nominal()).is_empty());
}
