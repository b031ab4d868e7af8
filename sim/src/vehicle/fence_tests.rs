//! The vehicle's geofence as each profile keeps it (`fence.rs`, [`Vehicle::check_fence`]): the
//! fence transfer beside the mission, the parameters per profile, enforcement and the breach
//! actions, driven through `handle` and `step` like the other vehicle tests.

use std::time::Instant;

use mavlink::dialects::ardupilotmega::{
    MavCmd, MavMessage, MavMissionResult, MavMissionType, MavResult, MavSeverity,
    COMMAND_LONG_DATA, MISSION_CLEAR_ALL_DATA, MISSION_COUNT_DATA, PARAM_SET_DATA,
};

use super::tests::{command, command_long, copter, rover, run_until, start_auto, upload, GCS};
use super::*;

const FENCE: MavMissionType = MavMissionType::MAV_MISSION_TYPE_FENCE;

/// A fence item at `north`, `east` metres from home: a polygon vertex, or with `Some(radius)`
/// an inclusion circle's centre.
fn area_item(v: &Vehicle, seq: u16, (north, east): (f64, f64), radius: Option<f32>) -> Item {
    let g = v.frame.to_geo(Ned {
        north,
        east,
        up: 0.0,
    });
    let (command, param1) = match radius {
        Some(r) => (MavCmd::MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION, r),
        None => (MavCmd::MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, 4.0),
    };
    Item {
        seq,
        command,
        param1,
        x: (g.lat_deg * 1e7).round() as i32,
        y: (g.lon_deg * 1e7).round() as i32,
        mission_type: FENCE,
        target_system: 1,
        ..Default::default()
    }
}

fn fence_count(v: &mut Vehicle, count: u16) -> Vec<MavMessage> {
    v.handle(
        GCS,
        &MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
            count,
            mission_type: FENCE,
            ..Default::default()
        }),
        Instant::now(),
    )
}

/// Uploads a fence of `vertices` and `circle` (centre, radius); returns the last replies.
fn upload_fence(
    v: &mut Vehicle,
    vertices: &[(f64, f64)],
    circle: Option<((f64, f64), f32)>,
) -> Vec<MavMessage> {
    let mut items: Vec<Item> = vertices
        .iter()
        .enumerate()
        .map(|(i, &at)| area_item(v, i as u16, at, None))
        .collect();
    if let Some((at, r)) = circle {
        items.push(area_item(v, items.len() as u16, at, Some(r)));
    }
    let out = fence_count(v, items.len() as u16);
    assert!(
        matches!(out.as_slice(), [MavMessage::MISSION_REQUEST_INT(r)] if r.mission_type == FENCE && r.seq == 0),
        "{out:?}"
    );
    let mut out = Vec::new();
    for item in items {
        out = v.handle(GCS, &MavMessage::MISSION_ITEM_INT(item), Instant::now());
    }
    out
}

/// The fence MISSION_ACK's result, if `out` is one, addressed to the ground station.
fn fence_ack(out: &[MavMessage]) -> Option<MavMissionResult> {
    match out {
        [MavMessage::MISSION_ACK(a)]
            if a.mission_type == FENCE && (a.target_system, a.target_component) == GCS =>
        {
            Some(a.mavtype)
        }
        _ => None,
    }
}

/// Steps until `f` holds (at most `max_s` simulated seconds); returns what was sent.
fn run_collect(
    v: &mut Vehicle,
    max_s: f64,
    mut f: impl FnMut(&Vehicle) -> bool,
) -> Vec<MavMessage> {
    let mut out = Vec::new();
    let mut t = 0.0;
    while !f(v) {
        out.extend(v.step(0.02));
        t += 0.02;
        assert!(t < max_s, "condition not met after {max_s} s");
    }
    out
}

/// The breaches logged: (which part, action).
fn breaches(v: &mut Vehicle) -> Vec<(String, String)> {
    v.take_log()
        .into_iter()
        .filter_map(|(_, e)| match e {
            LogEvent::FenceBreached { fence, action, .. } => Some((fence, action)),
            _ => None,
        })
        .collect()
}

/// The STATUSTEXTs of severity critical that announce a breach.
fn breach_texts(out: &[MavMessage]) -> Vec<String> {
    out.iter()
        .filter_map(|m| match m {
            MavMessage::STATUSTEXT(t) if t.severity == MavSeverity::MAV_SEVERITY_CRITICAL => {
                t.text.to_str().ok().map(str::to_owned)
            }
            _ => None,
        })
        .filter(|t| t.starts_with("Fence breached: "))
        .collect()
}

fn set_params(v: &mut Vehicle, params: &[(&str, f32)]) {
    for &(name, value) in params {
        assert!(v.params.set(name, value).is_some(), "{name}");
    }
}

#[test]
fn a_fence_upload_is_kept_apart_from_the_mission_and_a_breach_triggers_fence_action() {
    let mut v = rover();
    upload(&mut v, &[10.0, 80.0]);
    let square = [(-40.0, -40.0), (-40.0, 40.0), (40.0, 40.0), (40.0, -40.0)];
    let out = upload_fence(&mut v, &square, None);
    assert_eq!(
        fence_ack(&out),
        Some(MavMissionResult::MAV_MISSION_ACCEPTED)
    );
    assert_eq!(v.mission().len(), 3, "the mission is untouched");
    set_params(
        &mut v,
        &[
            ("FENCE_TYPE", 4.0),
            ("FENCE_ACTION", 2.0),
            ("FENCE_ENABLE", 1.0),
        ],
    );
    start_auto(&mut v);
    run_until(&mut v, 120.0, |v| v.behaviour() == Behaviour::Hold);
    assert_eq!(v.behaviour(), Behaviour::Hold, "held at the breach");
    let north = v.position().north;
    assert!(
        (40.0..50.0).contains(&north),
        "stopped near the fence: {north}"
    );
    assert_eq!(
        breaches(&mut v),
        [("polygon".to_owned(), "hold".to_owned())]
    );
}

/// The ArduPilot profiles enforce a circle item of the transfer under FENCE_TYPE's bit 4 (with
/// FENCE_ENABLE), beside the FENCE_RADIUS circle and the ceiling; the log tells its radius.
#[test]
fn ardupilot_enforces_a_circle_item_under_fence_type_bit_4() {
    for profile in [Profile::ArduPilot, Profile::ArduPilotResetting] {
        // (FENCE_ENABLE, FENCE_TYPE): a breach expected?
        for (enable, kinds, breach) in [(1.0, 4.0, true), (1.0, 3.0, false), (0.0, 4.0, false)] {
            let case = format!("{profile:?}, FENCE_ENABLE {enable}, FENCE_TYPE {kinds}");
            let mut v = rover();
            v.set_profile(profile);
            upload(&mut v, &[10.0, 80.0]);
            let out = upload_fence(&mut v, &[], Some(((0.0, 0.0), 30.0)));
            assert_eq!(
                fence_ack(&out),
                Some(MavMissionResult::MAV_MISSION_ACCEPTED),
                "{case}"
            );
            assert!(v.take_log().iter().any(|(_, e)| *e
                == LogEvent::FenceUploaded {
                    vertices: 0,
                    circle_m: Some(30.0)
                }));
            // FENCE_ACTION stays at its default, 1: RTL.
            set_params(&mut v, &[("FENCE_TYPE", kinds), ("FENCE_ENABLE", enable)]);
            start_auto(&mut v);
            let out = run_collect(&mut v, 200.0, |v| {
                v.behaviour() != Behaviour::Auto || v.target_seq().is_none()
            });
            if breach {
                assert_eq!(v.behaviour(), Behaviour::Rtl, "{case}");
                let north = v.position().north;
                assert!((30.0..40.0).contains(&north), "{case}: {north}");
                let texts = breach_texts(&out);
                assert_eq!(texts.len(), 1, "{case}: {texts:?}");
                assert!(
                    texts[0].starts_with("Fence breached: circle item (30 m"),
                    "{case}: {texts:?}"
                );
                assert_eq!(
                    breaches(&mut v),
                    [(
                        "circle item (30 m from its centre, radius 30 m)".to_owned(),
                        "rtl".to_owned()
                    )],
                    "{case}"
                );
            } else {
                let north = v.position().north;
                assert!(north > 70.0, "{case}: the mission flown, at {north}");
                assert!(breach_texts(&out).is_empty(), "{case}");
                assert!(breaches(&mut v).is_empty(), "{case}");
            }
        }
    }
}

/// A count of 0 and MISSION_CLEAR_ALL clear polygon and circle; both are logged as a
/// `fence_uploaded` of no vertices and no circle.
#[test]
fn clearing_the_fence_drops_polygon_and_circle() {
    let mut v = rover();
    let square = [(-40.0, -40.0), (-40.0, 40.0), (40.0, 40.0), (40.0, -40.0)];
    upload_fence(&mut v, &square, Some(((0.0, 0.0), 100.0)));
    assert!(v.take_log().iter().any(|(_, e)| *e
        == LogEvent::FenceUploaded {
            vertices: 4,
            circle_m: Some(100.0)
        }));
    assert_eq!(
        fence_ack(&fence_count(&mut v, 0)),
        Some(MavMissionResult::MAV_MISSION_ACCEPTED)
    );
    assert!(!v.fence.has_area());
    upload_fence(&mut v, &square, Some(((0.0, 0.0), 100.0)));
    let out = v.handle(
        GCS,
        &MavMessage::MISSION_CLEAR_ALL(MISSION_CLEAR_ALL_DATA {
            target_system: 1,
            mission_type: FENCE,
            ..Default::default()
        }),
        Instant::now(),
    );
    assert_eq!(
        fence_ack(&out),
        Some(MavMissionResult::MAV_MISSION_ACCEPTED)
    );
    assert!(!v.fence.has_area());
    let cleared: Vec<_> = v
        .take_log()
        .into_iter()
        .filter_map(|(_, e)| matches!(e, LogEvent::FenceUploaded { .. }).then_some(e))
        .collect();
    assert_eq!(
        cleared.last(),
        Some(&LogEvent::FenceUploaded {
            vertices: 0,
            circle_m: None
        })
    );
}

/// `--fence-capacity`: a fence transfer of more items is refused at its count with NO_SPACE
/// (the fence on board stays, nothing is logged); as many are taken.
#[test]
fn a_fence_transfer_above_the_capacity_is_answered_no_space() {
    let mut v = rover();
    assert_eq!(v.fence.capacity(), crate::fence::DEFAULT_CAPACITY);
    v.set_fence_capacity(3);
    let triangle = [(-40.0, -40.0), (-40.0, 40.0), (40.0, 0.0)];
    let out = upload_fence(&mut v, &triangle, None);
    assert_eq!(
        fence_ack(&out),
        Some(MavMissionResult::MAV_MISSION_ACCEPTED)
    );
    v.take_log();
    let out = fence_count(&mut v, 4);
    assert_eq!(
        fence_ack(&out),
        Some(MavMissionResult::MAV_MISSION_NO_SPACE)
    );
    assert_eq!(v.fence.vertices(), 3, "the fence on board stays");
    assert!(v.take_log().is_empty(), "a refusal is not an upload");
    // As many as the capacity start a transfer.
    assert!(matches!(fence_count(&mut v, 3).as_slice(),
        [MavMessage::MISSION_REQUEST_INT(r)] if r.seq == 0 && r.mission_type == FENCE));
}

/// PX4 keeps GF_* and no FENCE_*: a ground station setting FENCE_ENABLE gets no answer (an
/// unknown name), GF_ACTION is answered; switching back restores ArduPilot's table.
#[test]
fn px4_keeps_gf_params_and_no_fence_params() {
    let mut v = rover();
    let set = |v: &mut Vehicle, name: &str, value: f32| {
        v.handle(
            GCS,
            &MavMessage::PARAM_SET(PARAM_SET_DATA {
                target_system: 1,
                param_id: name.into(),
                param_value: value,
                ..Default::default()
            }),
            Instant::now(),
        )
    };
    assert_eq!(set(&mut v, "FENCE_ENABLE", 1.0).len(), 1);
    assert!(set(&mut v, "GF_ACTION", 3.0).is_empty());
    v.set_profile(Profile::Px4);
    assert!(
        set(&mut v, "FENCE_ENABLE", 1.0).is_empty(),
        "unknown on PX4"
    );
    let out = set(&mut v, "GF_ACTION", 3.0);
    assert!(
        matches!(out.as_slice(), [MavMessage::PARAM_VALUE(p)]
            if p.param_id.to_str().ok() == Some("GF_ACTION") && p.param_value == 3.0),
        "{out:?}"
    );
    for name in ["GF_MAX_HOR_DIST", "GF_MAX_VER_DIST"] {
        assert_eq!(v.params.get_or(name, -1.0), 0.0, "{name}");
    }
    v.set_profile(Profile::Generic);
    assert!(v.params.by_name("GF_ACTION").is_none());
    assert_eq!(
        v.params.get_or("FENCE_ENABLE", -1.0),
        0.0,
        "ArduPilot's default"
    );
}

/// PX4 keeps no FENCE_* switch: an area uploaded is in force, and GF_ACTION (hold by
/// default) acts on a breach.
#[test]
fn a_px4_vehicle_enforces_an_uploaded_circle_with_gf_action() {
    let mut v = rover();
    v.set_profile(Profile::Px4);
    assert!(v.params.by_name("FENCE_ENABLE").is_none());
    assert_eq!(v.params.get_or("GF_ACTION", -1.0), 2.0);
    upload(&mut v, &[10.0, 80.0]);
    let out = upload_fence(&mut v, &[], Some(((0.0, 0.0), 30.0)));
    assert_eq!(
        fence_ack(&out),
        Some(MavMissionResult::MAV_MISSION_ACCEPTED)
    );
    assert_eq!(
        command(&mut v, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0),
        MavResult::MAV_RESULT_ACCEPTED
    );
    assert_eq!(
        command(&mut v, MavCmd::MAV_CMD_MISSION_START, 0.0, 0.0),
        MavResult::MAV_RESULT_ACCEPTED
    );
    run_until(&mut v, 120.0, |v| v.behaviour() == Behaviour::Hold);
    assert_eq!(v.behaviour(), Behaviour::Hold, "held at the breach");
    let north = v.position().north;
    assert!(
        (30.0..40.0).contains(&north),
        "stopped near the circle: {north}"
    );
    let log = v.take_log();
    assert!(log.iter().any(|(_, e)| matches!(e,
        LogEvent::FenceUploaded { vertices: 0, circle_m: Some(r) } if *r == 30.0)));
    assert!(log.iter().any(
        |(_, e)| matches!(e, LogEvent::FenceBreached { fence, action, .. }
            if fence.starts_with("circle item") && action == "hold")
    ));
}

/// A PX4 rover driving its mission north (items at 10 and 80 m) past GF_MAX_HOR_DIST (20 m
/// from home; no area uploaded): what each GF_ACTION does. Without a limit or an area, or
/// with GF_ACTION 0, nothing is enforced.
#[test]
fn px4_gf_action_picks_the_breach_action_of_a_rover() {
    // (GF_ACTION, GF_MAX_HOR_DIST, behaviour after, the action logged)
    let cases: [(f32, f32, Behaviour, Option<&str>); 7] = [
        (0.0, 20.0, Behaviour::Auto, None),
        (2.0, 0.0, Behaviour::Auto, None),
        (1.0, 20.0, Behaviour::Auto, Some("warning")),
        (2.0, 20.0, Behaviour::Hold, Some("hold")),
        (3.0, 20.0, Behaviour::Rtl, Some("rtl")),
        // A rover has no land mode: it holds, and terminate says what it did instead.
        (4.0, 20.0, Behaviour::Hold, Some("terminate as hold")),
        (5.0, 20.0, Behaviour::Hold, Some("hold")),
    ];
    for (action, max_hor, after, logged) in cases {
        let case = format!("GF_ACTION {action}, GF_MAX_HOR_DIST {max_hor}");
        let mut v = rover();
        v.set_profile(Profile::Px4);
        upload(&mut v, &[10.0, 80.0]);
        set_params(
            &mut v,
            &[("GF_ACTION", action), ("GF_MAX_HOR_DIST", max_hor)],
        );
        assert_eq!(
            command(&mut v, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert_eq!(
            command(&mut v, MavCmd::MAV_CMD_MISSION_START, 0.0, 0.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        // Until the action took effect, or the mission (past 20 m) is over.
        let out = run_collect(&mut v, 200.0, |v| {
            v.behaviour() != Behaviour::Auto || v.position().north > 30.0
        });
        let north = v.position().north;
        let found = breaches(&mut v);
        match logged {
            Some(logged) => {
                assert_eq!(found.len(), 1, "{case}: {found:?}");
                assert_eq!(found[0].0, "circle (20 m from home, radius 20 m)", "{case}");
                assert_eq!(found[0].1, logged, "{case}");
                let texts = breach_texts(&out);
                assert_eq!(texts.len(), 1, "{case}: {texts:?}");
                assert!(texts[0].contains("fence") || texts[0].contains("Fence"));
                assert!(texts[0].contains("breach"));
            }
            None => {
                assert!(found.is_empty(), "{case}: {found:?}");
                assert!(breach_texts(&out).is_empty(), "{case}");
            }
        }
        assert_eq!(v.behaviour(), after, "{case}");
        if after != Behaviour::Auto {
            assert!((20.0..30.0).contains(&north), "{case}: acted at {north}");
        }
    }
}

/// A PX4 copter climbing past GF_MAX_VER_DIST: land (also for terminate, said so), hold is
/// its loiter, return its RTL; the heartbeat's PX4 mode follows.
#[test]
fn px4_gf_action_lands_a_copter_at_the_ceiling() {
    let cases = [
        (2.0, Behaviour::Hold, "loiter", (4, 3)),
        (3.0, Behaviour::Rtl, "rtl", (4, 5)),
        (4.0, Behaviour::Land, "terminate as land", (4, 6)),
        (5.0, Behaviour::Land, "land", (4, 6)),
    ];
    for (action, after, logged, (main, sub)) in cases {
        let mut v = copter();
        v.set_profile(Profile::Px4);
        set_params(&mut v, &[("GF_ACTION", action), ("GF_MAX_VER_DIST", 5.0)]);
        assert_eq!(
            command(&mut v, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        // PX4's OFFBOARD-like GUIDED (main mode 6), then a take-off to 10 m.
        assert_eq!(
            command(&mut v, MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 6.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert_eq!(
            command_long(
                &mut v,
                COMMAND_LONG_DATA {
                    command: MavCmd::MAV_CMD_NAV_TAKEOFF,
                    param7: 10.0,
                    ..Default::default()
                }
            ),
            MavResult::MAV_RESULT_ACCEPTED
        );
        let out = run_collect(&mut v, 60.0, |v| v.behaviour() != Behaviour::Guided);
        assert_eq!(v.behaviour(), after, "GF_ACTION {action}");
        let up = v.position().up;
        assert!(
            (5.0..6.0).contains(&up),
            "GF_ACTION {action}: acted at {up} m"
        );
        assert_eq!(
            breaches(&mut v),
            [("ceiling (5 m, max 5 m)".to_owned(), logged.to_owned())],
            "GF_ACTION {action}"
        );
        assert_eq!(breach_texts(&out).len(), 1, "GF_ACTION {action}");
        assert_eq!(
            v.profile.encode_mode(v.cfg.kind, v.mode),
            main << 16 | sub << 24,
            "GF_ACTION {action}"
        );
    }
}
