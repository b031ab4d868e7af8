//! Random sequences of in-flight inputs, nonsense arguments included: the executive never
//! panics and hands out finite positions.

use super::*;

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
        let plan = check::load(&src, &VehicleParams::rover()).unwrap();
        let ids: Vec<String> = ["hold", "area", "laps", "laps.1", "check", "wait", "departure.2", "nope"]
            .iter().map(|s| s.to_string()).collect();
        let attrs = ["spacing", "length", "width", "speed", "alt", "sweepAngle", "fix", "type"];
        let vars = ["inspect", "laps", "battery", "alt", "iteration", "ghost"];
        let mut ex = Executive::from_checked(plan.clone());
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
