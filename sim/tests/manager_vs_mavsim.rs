//! The MAVLink communication manager driving the real mavsim binary, over UDP and over a pty.

mod common;

use std::time::Duration;

use common::{bounded, line_mission, start_mission, Sim, Via, HOME};
use vas::mavlink_cm::dialect::{MavCmd, MavMissionResult, MavResult};
use vas::mavlink_cm::{CommandError, MavEvent, MissionError, MissionItem, ParamError, Telemetry};

/// Upload, download, partial write, clear: the mission protocol end to end.
async fn mission_round_trips(via: Via) {
    let sim = Sim::start(via, &[]).await;
    let mgr = sim.manager().await;

    let items = line_mission(6, 15.0, 0.0);
    bounded("upload", mgr.mission_upload(&items))
        .await
        .expect("upload");
    let down = bounded("download", mgr.mission_download())
        .await
        .expect("download");
    assert_eq!(down.len(), items.len());
    // Item 0 is the vehicle's home, whatever we sent there (ArduPilot behaviour).
    assert_eq!(down[1..], items[1..]);
    assert!((down[0].lat_deg() - HOME.0).abs() < 1e-6);

    // Partial write of items 2..=3.
    let replacement = line_mission(2, 50.0, 30.0)[1..].to_vec();
    bounded("partial", mgr.mission_write_partial(2, &replacement))
        .await
        .expect("partial write");
    let down = bounded("download", mgr.mission_download())
        .await
        .expect("download");
    let mut expected = items.clone();
    expected[2..4].clone_from_slice(&replacement);
    assert_eq!(down[1..], expected[1..]);
    assert_eq!(mgr.mission_cached()[1..], expected[1..]);

    // A partial write cannot grow the mission.
    let err = bounded("bad partial", mgr.mission_write_partial(6, &replacement))
        .await
        .unwrap_err();
    assert_eq!(
        err,
        MissionError::Rejected(MavMissionResult::MAV_MISSION_INVALID_SEQUENCE)
    );

    let uploads = sim.log_events("mission_uploaded");
    assert_eq!(uploads.len(), 1);
    assert_eq!(uploads[0]["count"], 7);
    let partials = sim.log_events("mission_partial_write");
    assert_eq!(partials.len(), 1);
    assert_eq!(
        (partials[0]["start"].as_u64(), partials[0]["end"].as_u64()),
        (Some(2), Some(3))
    );

    bounded("clear", mgr.mission_clear()).await.expect("clear");
    let down = bounded("download", mgr.mission_download())
        .await
        .expect("download");
    assert_eq!(down.len(), 1, "only home is left");
    mgr.shutdown().await;
    sim.stop().await;
}

/// Modes, arming, set-current, parameters and telemetry.
async fn control_and_params(via: Via) {
    let sim = Sim::start(via, &[]).await;
    let mgr = sim.manager().await;
    let mut events = mgr.subscribe();

    // AUTO without a mission is refused, as ArduPilot does.
    let err = bounded("auto", mgr.set_mode("AUTO")).await.unwrap_err();
    assert_eq!(
        err,
        CommandError::Rejected {
            command: MavCmd::MAV_CMD_DO_SET_MODE,
            result: MavResult::MAV_RESULT_FAILED
        }
    );
    assert!(matches!(
        mgr.set_mode("NO_SUCH_MODE").await,
        Err(CommandError::UnknownMode(_))
    ));

    bounded("upload", mgr.mission_upload(&line_mission(4, 200.0, 0.0)))
        .await
        .expect("upload");
    bounded("set current", mgr.mission_set_current(3))
        .await
        .expect("set current");
    assert_eq!(mgr.state().mission_current, Some(3));

    bounded("arm", mgr.arm(true)).await.expect("arm");
    assert!(mgr.state().armed);
    bounded("auto", mgr.set_mode("AUTO")).await.expect("auto");
    assert_eq!(mgr.state().mode, Some(10));
    assert_eq!(mgr.state().mode_name, Some("AUTO"));
    // Entering AUTO keeps the current index chosen before.
    assert_eq!(mgr.state().mission_current, Some(3));
    bounded("set current in auto", mgr.mission_set_current(2))
        .await
        .expect("set current");
    bounded("hold", mgr.set_mode(4u32))
        .await
        .expect("hold by number");
    assert_eq!(mgr.state().mode_name, Some("HOLD"));
    bounded("disarm", mgr.arm(false)).await.expect("disarm");
    assert!(!mgr.state().armed);

    // The mode change reached the event stream too.
    let saw_auto = bounded("mode event", async {
        loop {
            if let Ok(MavEvent::ModeChanged { to: 10, .. }) = events.recv().await {
                return true;
            }
        }
    })
    .await;
    assert!(saw_auto);

    // Parameters.
    let all = bounded("param list", mgr.params_list())
        .await
        .expect("list");
    assert_eq!(all.get("WP_RADIUS"), Some(&2.0));
    assert_eq!(all.get("SYSID_THISMAV"), Some(&1.0));
    assert!(all.len() >= 10);
    assert_eq!(
        bounded("set", mgr.param_set("CRUISE_SPEED", 3.5))
            .await
            .expect("set"),
        3.5
    );
    assert_eq!(
        bounded("get", mgr.param_get("CRUISE_SPEED"))
            .await
            .expect("get"),
        3.5
    );
    assert_eq!(mgr.param_cached("CRUISE_SPEED"), Some(3.5));
    let err = bounded("unknown", mgr.param_get("NO_SUCH_PARAM"))
        .await
        .unwrap_err();
    assert!(
        matches!(err, ParamError::RetriesExhausted { .. }),
        "{err:?}"
    );

    // Telemetry at a requested rate.
    bounded(
        "rates",
        mgr.request_telemetry(&[(Telemetry::Position, 10.0), (Telemetry::Attitude, 5.0)]),
    )
    .await
    .expect("rates");
    let pos = bounded("position", async {
        loop {
            if let Ok(MavEvent::Position(p)) = events.recv().await {
                return p;
            }
        }
    })
    .await;
    assert!((pos.lat_deg - HOME.0).abs() < 0.01);

    let arming: Vec<bool> = sim
        .log_events("armed")
        .iter()
        .filter_map(|r| r["armed"].as_bool())
        .collect();
    assert_eq!(arming, [true, false]);
    let modes: Vec<u64> = sim
        .log_events("mode_changed")
        .iter()
        .filter_map(|r| r["to"].as_u64())
        .collect();
    assert_eq!(modes, [10, 4]);
    let currents: Vec<u64> = sim
        .log_events("current_changed")
        .iter()
        .filter_map(|r| r["seq"].as_u64())
        .collect();
    assert_eq!(currents, [3, 3, 2], "set 3, AUTO resumes at 3, set 2");
    mgr.shutdown().await;
    sim.stop().await;
}

#[tokio::test]
async fn udp_mission_round_trips() {
    mission_round_trips(Via::Udp).await;
}

#[tokio::test]
async fn udp_control_and_params() {
    control_and_params(Via::Udp).await;
}

#[tokio::test]
async fn pty_mission_round_trips() {
    mission_round_trips(Via::Pty).await;
}

#[tokio::test]
async fn pty_control_and_params() {
    control_and_params(Via::Pty).await;
}

/// Flies a small AUTO mission at 20× and checks the reached sequence both from
/// the manager's events and from mavsim's log: in order, none skipped or
/// repeated, HOLD at the end.
#[tokio::test]
async fn auto_mission_at_speedup_20() {
    let sim = Sim::start(Via::Udp, &["--speedup", "20"]).await;
    let mgr = sim.manager().await;
    let items = line_mission(5, 20.0, 5.0);
    let mut events = start_mission(&mgr, &items).await;

    // 100 m at 2 m/s is 50 simulated seconds, 2.5 s of wall time.
    let reached = tokio::time::timeout(Duration::from_secs(60), async {
        let mut reached = Vec::new();
        loop {
            match events.recv().await {
                Ok(MavEvent::WaypointReached { seq, .. }) => reached.push(seq),
                Ok(MavEvent::ModeChanged { to: 4, .. }) => return reached,
                Ok(_) => {}
                Err(e) => panic!("event stream: {e}"),
            }
        }
    })
    .await
    .expect("the rover finished the mission and switched to HOLD");
    assert_eq!(reached, [1, 2, 3, 4, 5]);
    assert_eq!(mgr.state().mode_name, Some("HOLD"));

    let log_reached = sim.log_events("item_reached");
    let seqs: Vec<u64> = log_reached
        .iter()
        .filter_map(|r| r["seq"].as_u64())
        .collect();
    assert_eq!(seqs, [1, 2, 3, 4, 5]);
    for r in &log_reached {
        let seq = r["seq"].as_u64().unwrap() as usize;
        let item: &MissionItem = &items[seq];
        assert!((r["lat"].as_f64().unwrap() - item.lat_deg()).abs() < 1e-7);
        assert!((r["lon"].as_f64().unwrap() - item.lon_deg()).abs() < 1e-7);
    }
    assert_eq!(sim.log_events("mission_complete").len(), 1);
    mgr.shutdown().await;
    sim.stop().await;
}

/// The manager as a good ground-station citizen: it listens only to the configured system on a
/// shared link, reads AUTOPILOT_VERSION's capabilities, and knows the PX4 profile's conventions
/// (family from the heartbeat, PX4 modes, no partial writes found out by one short probe; its
/// time is `vas.partial_write_probe_ms` in the waypoint benchmark).
#[tokio::test]
async fn routing_capabilities_and_the_px4_profile() {
    use common::connect;
    use vas::mavlink_cm::{AutopilotFamily, LinkError, ManagerConfig, MavlinkManager};
    let sim = Sim::start(Via::Udp, &["--sysid", "7", "--autopilot", "px4"]).await;
    // Another vehicle's id: nothing is heard.
    let other = ManagerConfig {
        target_system: Some(3),
        ..ManagerConfig::default()
    };
    let mgr = MavlinkManager::open(&sim.endpoint, other).await.unwrap();
    let heard = mgr.wait_connected(std::time::Duration::from_secs(3)).await;
    assert!(
        matches!(heard, Err(LinkError::NotConnected(_))),
        "{heard:?}"
    );
    mgr.shutdown().await;
    // Its own id: connected, a PX4 by its heartbeat.
    let mine = ManagerConfig {
        target_system: Some(7),
        ..ManagerConfig::default()
    };
    let mgr = connect(&sim.endpoint, mine).await;
    assert_eq!(mgr.family(), AutopilotFamily::Px4);
    assert!(mgr.state().px4_modes);
    let caps = bounded("capabilities", mgr.request_capabilities())
        .await
        .expect("capabilities")
        .expect("mavsim reports AUTOPILOT_VERSION");
    assert_ne!(caps & 4, 0, "MISSION_INT");
    let partial = bounded("probe", mgr.probe_partial_writes())
        .await
        .expect("probe");
    assert!(!partial, "the px4 profile has no partial writes");
    assert_eq!(mgr.partial_writes(), Some(false));
    // PX4 modes: AUTO.LOITER by name, confirmed by the heartbeat.
    start_mission(&mgr, &line_mission(3, 15.0, 0.0)).await;
    assert_eq!(mgr.state().mode, Some(4 << 16 | 4 << 24));
    assert_eq!(mgr.state().mode_name, Some("AUTO"));
    mgr.shutdown().await;
    sim.stop().await;
}
