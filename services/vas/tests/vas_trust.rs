//! What the VAS trusts (issue 13), the real `vas` and `mavsim` binaries over UDP MAVLink: a
//! signed link flies and commands normally; pushed waypoints outside the globe, the altitude
//! bound or the count caps are refused naming the waypoint and the field.

mod common;

use std::os::unix::fs::PermissionsExt;

use common::*;
use usal_types::{FlightState, Waypoint};

fn wp(seq: u64, lat: f64, lon: f64, alt: f64) -> Waypoint {
    Waypoint {
        seq,
        lat,
        lon,
        alt,
        leg: "t".into(),
        ..Waypoint::default()
    }
}

/// VAS and mavsim share a signing key: the VAS configures the autopilot and its commands are
/// obeyed (PARKING, then DIRECTED puts mavsim in MANUAL), waypoints fly.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_signed_link_flies_and_commands_normally() {
    let dir = tempfile::tempdir().unwrap();
    let key = dir.path().join("mav.key");
    std::fs::write(&key, "c3".repeat(32)).unwrap();
    std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o600)).unwrap();
    let cfg = dir.path().join("vas.xml");
    std::fs::write(
        &cfg,
        format!(
            r#"<vas><signing keyFile="{}" linkId="1"/></vas>"#,
            key.display()
        ),
    )
    .unwrap();
    let key_arg = key.to_str().unwrap();
    let sim = Sim::start_with(
        "127.0.0.1:0",
        10.0,
        &dir.path().join("sim.jsonl"),
        &["--signing-key", key_arg],
    )
    .await;
    let domain = unique_domain("signed");
    let vas = VasProc::start(
        &format!("udpout:{}", sim.addr),
        &domain,
        &["-c", cfg.to_str().unwrap()],
    );
    let g = Ground::open(&domain).await;
    g.wait_state(FlightState::Parking, STEP).await;
    g.push_all(&zigzag(3, 10.0)).await;
    g.request(FlightState::WaypointNavigation)
        .await
        .expect("WAYPOINT_NAVIGATION over the signed link");
    for _ in 0..3 {
        tokio::time::timeout(STEP, g.reached.recv())
            .await
            .expect("waypoint reached in time")
            .expect("waypoint_reached");
    }
    assert!(!sim.log_events("mission_uploaded").is_empty());
    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_waypoints_are_refused_naming_the_index_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("vas.xml");
    std::fs::write(
        &cfg,
        r#"<vas maxAltitudeM="500" maxWaypointsPerCall="4" maxQueuedWaypoints="6"/>"#,
    )
    .unwrap();
    let sim = Sim::start("127.0.0.1:0", 10.0, &dir.path().join("sim.jsonl")).await;
    let domain = unique_domain("limits");
    let vas = VasProc::start(
        &format!("udpout:{}", sim.addr),
        &domain,
        &["-c", cfg.to_str().unwrap()],
    );
    let g = Ground::open(&domain).await;
    g.wait_state(FlightState::Parking, STEP).await;
    let (lat, lon) = (HOME.0, HOME.1);
    let refused = |wps: Vec<Waypoint>| {
        let push = &g.push;
        async move {
            match push.call(&wps, STEP).await {
                Err(marea::CallError::Remote { message, .. }) => message,
                other => panic!("expected a refusal, got {other:?}"),
            }
        }
    };
    let e = refused(vec![wp(0, lat, lon, 0.0), wp(1, 91.0, lon, 0.0)]).await;
    assert!(e.contains("waypoint 1 (seq 1): lat 91"), "{e}");
    let e = refused(vec![wp(0, lat, f64::NAN, 0.0)]).await;
    assert!(e.contains("waypoint 0 (seq 0): lon NaN"), "{e}");
    let e = refused(vec![wp(0, lat, lon, 501.0)]).await;
    assert!(e.contains("alt 501"), "{e}");
    let e = refused((0..5).map(|i| wp(i, lat, lon, 0.0)).collect()).await;
    assert!(e.contains("5 waypoints in one call: at most 4"), "{e}");

    // Nothing refused was queued; good ones are, up to the queue cap.
    let ok: Vec<Waypoint> = zigzag(4, 10.0);
    let q = g.push.call(&ok, STEP).await.expect("a good push");
    assert_eq!(q.queued, 4);
    let more: Vec<Waypoint> = zigzag(7, 10.0)[4..].to_vec();
    let e = refused(more).await;
    assert!(e.contains("at most 6 queued"), "{e}");
    assert!(sim.log_events("mission_uploaded").is_empty());
    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}
