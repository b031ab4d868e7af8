//! What the VAS trusts, the real `vas` and `mavsim` binaries over UDP MAVLink: a signed link
//! flies and commands normally; pushed waypoints outside the globe, the altitude bound or the
//! count caps are refused naming the waypoint and the field.

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

/// A node that publishes `fmo/manual_control` as the FMo does.
struct Sticks {
    node: marea::Node,
    var: marea::Variable<usal_types::ManualCommand>,
}

impl Sticks {
    async fn open(domain: &str, name: &str) -> Sticks {
        let mut cfg = marea::NetworkConfig::ethernet_loopback(name);
        cfg.domain = domain.to_owned();
        let node = marea::Node::open(&cfg).await.expect("node");
        let svc = node.service("fmo").expect("service");
        let var = svc.publish_variable("manual_control").expect("publish");
        Sticks { node, var }
    }

    /// Full throttle for rover1 at 20 Hz for `how_long`, stamped `ahead_ms` into the future.
    async fn drive(&self, how_long: std::time::Duration, ahead_ms: u64) {
        let end = tokio::time::Instant::now() + how_long;
        let mut tick = tokio::time::interval(std::time::Duration::from_millis(50));
        while tokio::time::Instant::now() < end {
            tick.tick().await;
            let now = std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .unwrap()
                .as_millis() as u64;
            let cmd = usal_types::ManualCommand {
                target: "rover1/vas".into(),
                sticks: usal_types::ManualControl {
                    throttle: 0.8,
                    timestamp_ms: now + ahead_ms,
                    ..Default::default()
                },
            };
            self.var.set(&cmd).expect("set");
        }
    }
}

/// Metres between two positions (flat earth, short distances).
fn metres(a: &usal_types::Position, b: &usal_types::Position) -> f64 {
    let dn = (a.lat - b.lat) * 111_319.5;
    let de = (a.lon - b.lon) * 111_319.5 * a.lat.to_radians().cos();
    (dn * dn + de * de).sqrt()
}

/// Manual control is obeyed only from the configured station, and not when stamped beyond the
/// skew into the future; the refusals are raised as alarms naming the node.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn manual_control_only_from_the_configured_station() {
    let dir = tempfile::tempdir().unwrap();
    let sim = Sim::start("127.0.0.1:0", 2.0, &dir.path().join("sim.jsonl")).await;
    let domain = unique_domain("manual");
    let vas = VasProc::start(
        &format!("udpout:{}", sim.addr),
        &domain,
        &["--manual-stations", "station-ok"],
    );
    let g = Ground::open(&domain).await;
    let position = g
        .svc
        .subscribe_variable::<usal_types::Position>("rover1/vas/position")
        .unwrap();
    g.wait_state(FlightState::Parking, STEP).await;
    g.request(FlightState::ManualNavigation)
        .await
        .expect("MANUAL_NAVIGATION");
    let here = || async {
        tokio::time::timeout(STEP, position.recv())
            .await
            .expect("position in time")
            .expect("position")
            .value
    };

    let intruder = Sticks::open(&domain, "intruder").await;
    let p0 = here().await;
    let drive = intruder.drive(std::time::Duration::from_secs(3), 0);
    let (_, alarm) = tokio::join!(drive, g.wait_alarm("node intruder", STEP));
    assert!(
        alarm.text.contains("not a configured station"),
        "{}",
        alarm.text
    );
    let p1 = here().await;
    assert!(metres(&p0, &p1) < 0.3, "the intruder drove the rover");

    let station = Sticks::open(&domain, "station-ok").await;
    let drive = station.drive(std::time::Duration::from_secs(2), 60_000);
    let (_, alarm) = tokio::join!(drive, g.wait_alarm("ahead of our clock", STEP));
    assert!(alarm.text.contains("node station-ok"), "{}", alarm.text);
    let p2 = here().await;
    assert!(
        metres(&p1, &p2) < 0.3,
        "a sample from the future drove the rover"
    );

    station.drive(std::time::Duration::from_secs(3), 0).await;
    let p3 = here().await;
    assert!(
        metres(&p2, &p3) > 1.0,
        "the configured station did not drive the rover"
    );

    intruder.node.shutdown().await;
    station.node.shutdown().await;
    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}
