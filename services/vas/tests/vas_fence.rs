//! The geofence on the VAS, with the `vas` and `mavsim` binaries over UDP: `set_fence` uploads
//! it to the autopilot (mavsim logs the polygon it received), waypoints outside it are refused
//! naming the waypoint, and when the fence is tightened under a moving rover, mavsim's
//! enforcement holds it (its `FENCE_ACTION`) and the VAS raises the breach as a `failsafe`
//! event. A restarted autopilot gets the fence again.

mod common;

use std::time::Duration;

use common::*;
use usal_types::{Failsafe, FailsafeKind, Fence, FenceAction, FlightState, Home, Waypoint};

/// A point `north`, `east` metres from home.
fn at(north: f64, east: f64) -> (f64, f64) {
    let m_per_deg_lat = 111_319.49;
    let m_per_deg_lon = m_per_deg_lat * HOME.0.to_radians().cos();
    (
        HOME.0 + north / m_per_deg_lat,
        HOME.1 + east / m_per_deg_lon,
    )
}

fn fence(max_distance_m: f64) -> Fence {
    Fence {
        home: HOME,
        max_distance_m: Some(max_distance_m),
        max_height_m: Some(50.0),
        polygon: vec![
            at(-150.0, -150.0),
            at(-150.0, 150.0),
            at(150.0, 150.0),
            at(150.0, -150.0),
        ],
        action: FenceAction::Hold,
    }
}

async fn run() {
    let dir = tempfile::tempdir().unwrap();
    let sim = Sim::start("127.0.0.1:0", 5.0, &dir.path().join("sim.jsonl")).await;
    let domain = unique_domain("fence");
    let vas = VasProc::start(&format!("udpout:{}", sim.addr), &domain, &[]);
    let g = Ground::open(&domain).await;
    let set_fence = g
        .svc
        .function::<Option<Fence>, String>("rover1/vas/set_fence")
        .unwrap();
    let failsafes = g
        .svc
        .subscribe_event::<Failsafe>("rover1/vas/failsafe")
        .unwrap();
    g.wait_state(FlightState::Parking, STEP).await;

    let reply = set_fence
        .call(&Some(fence(120.0)), STEP)
        .await
        .expect("set_fence");
    assert!(reply.contains("uploaded to the autopilot"), "{reply}");
    let up = sim.log_events("fence_uploaded");
    assert_eq!(
        up.last().map(|r| r["vertices"].clone()),
        Some(4.into()),
        "{up:?}"
    );

    // Outside the circle: refused whole, naming the waypoint; mavsim never gets it.
    let mut wps = zigzag(3, 10.0);
    let far = at(200.0, 0.0);
    wps[2].lat = far.0;
    wps[2].lon = far.1;
    let e = g.push.call(&wps, STEP).await.unwrap_err().to_string();
    assert!(
        e.contains("waypoint 2 (seq 2) outside the fence") && e.contains("(fence: 120 m)"),
        "{e}"
    );
    let refused = tokio::time::timeout(STEP, failsafes.recv())
        .await
        .expect("a failsafe event")
        .expect("failsafe");
    assert_eq!(refused.value.kind, FailsafeKind::Fence);
    assert_eq!(refused.value.action, "refused");
    // A bad fence is refused as a whole.
    let mut bad = fence(120.0);
    bad.polygon.truncate(2);
    let e = set_fence
        .call(&Some(bad), STEP)
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("at least 3"), "{e}");

    // Inside: flown. Then the fence shrinks to 40 m under the moving rover: mavsim holds it.
    let wps: Vec<Waypoint> = zigzag(10, 10.0);
    g.push_all(&wps).await;
    g.request(FlightState::WaypointNavigation)
        .await
        .expect("navigation");
    sim.wait_log("item_reached", STEP, "the rover does not drive", |r| {
        r.len() >= 5
    })
    .await;
    let reply = set_fence
        .call(&Some(fence(40.0)), STEP)
        .await
        .expect("tighter fence");
    assert!(reply.contains("uploaded"), "{reply}");
    let breach = loop {
        let f = tokio::time::timeout(STEP, failsafes.recv())
            .await
            .expect("a breach failsafe")
            .expect("failsafe");
        if f.value.kind == FailsafeKind::Fence && f.value.action == "autopilot" {
            break f.value;
        }
    };
    assert!(breach.text.contains("Fence breached: circle"), "{breach:?}");
    g.wait_state(FlightState::Parking, STEP).await;
    let log = sim.log_events("fence_breached");
    assert_eq!(log.len(), 1, "{log:?}");
    assert_eq!(log[0]["action"], "hold");

    // The autopilot restarts (same port, a new log): the VAS uploads the fence again.
    let addr = sim.addr.clone();
    sim.kill().await;
    g.wait_alarm("heartbeat lost", STEP).await;
    let sim = Sim::start(&addr, 5.0, &dir.path().join("sim2.jsonl")).await;
    sim.wait_log(
        "fence_uploaded",
        STEP * 2,
        "the fence was not uploaded to the restarted autopilot",
        |r| !r.is_empty(),
    )
    .await;
    assert_eq!(sim.log_events("fence_uploaded")[0]["vertices"], 4);

    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fence_uploaded_enforced_and_waypoints_outside_refused() {
    tokio::time::timeout(Duration::from_secs(180), run())
        .await
        .expect("the test took too long");
}

/// The vehicle's own fence (`vas --fence`, what `usal run` gives from the mission), on
/// `profile`'s autopilot: uploaded before the rover may start, never taken down by a plan
/// without a fence, narrowed by a plan's fence and never widened by one, and enforced by the
/// autopilot (a breach under the moving rover).
async fn vehicle_fence_on(profile: &str) {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("fence.xml");
    let pts: String = [
        (-150.0, -150.0),
        (-150.0, 150.0),
        (150.0, 150.0),
        (150.0, -150.0),
    ]
    .iter()
    .map(|&(n, e)| {
        let (lat, lon) = at(n, e);
        format!(r#"<pt lat="{lat}" lon="{lon}"/>"#)
    })
    .collect();
    std::fs::write(
        &file,
        format!(
            r#"<fence maxDistance="200" homeLat="{}" homeLon="{}" action="hold">{pts}</fence>"#,
            HOME.0, HOME.1
        ),
    )
    .unwrap();
    let sim = Sim::start_with(
        "127.0.0.1:0",
        5.0,
        &dir.path().join("sim.jsonl"),
        &["--autopilot", profile],
    )
    .await;
    let domain = unique_domain("vfence");
    let vas = VasProc::start(
        &format!("udpout:{}", sim.addr),
        &domain,
        &["--fence", file.to_str().unwrap()],
    );
    let g = Ground::open(&domain).await;
    let set_fence = g
        .svc
        .function::<Option<Fence>, String>("rover1/vas/set_fence")
        .unwrap();
    let failsafes = g
        .svc
        .subscribe_event::<Failsafe>("rover1/vas/failsafe")
        .unwrap();
    g.wait_state(FlightState::Parking, STEP).await;
    sim.wait_log(
        "fence_uploaded",
        STEP,
        "the vehicle's fence never reached the autopilot",
        |r| r.iter().any(|r| r["vertices"] == 4),
    )
    .await;
    // The stations' map: the autopilot's home (its HOME_POSITION) and the fence in force.
    let home = g.svc.subscribe_variable::<Home>("rover1/vas/home").unwrap();
    let home = tokio::time::timeout(STEP, home.recv())
        .await
        .expect("no home published")
        .unwrap()
        .value;
    assert!(
        (home.lat - HOME.0).abs() < 1e-6 && (home.lon - HOME.1).abs() < 1e-6,
        "home {home:?}, the simulator's is {HOME:?}"
    );
    let in_force = g
        .svc
        .subscribe_variable::<Fence>("rover1/vas/fence")
        .unwrap();
    let in_force = tokio::time::timeout(STEP, in_force.recv())
        .await
        .expect("no fence published")
        .unwrap()
        .value;
    assert_eq!(
        (in_force.max_distance_m, in_force.polygon.len()),
        (Some(200.0), 4),
        "{in_force:?}"
    );
    if profile == "px4" {
        // PX4 keeps the circle as an inclusion item of the transfer, around the fence's home.
        assert!(
            sim.log_events("fence_uploaded")
                .iter()
                .any(|r| r["circle_m"] == 200.0),
            "{:?}",
            sim.log_events("fence_uploaded")
        );
    }

    // A plan without a fence: the vehicle's stays, on the VAS and on the autopilot.
    let reply = set_fence.call(&None, STEP).await.expect("no plan fence");
    assert!(reply.contains("fence in force"), "{reply}");
    let e = g
        .push
        .call(&vec![wp_at(1, at(180.0, 0.0))], STEP)
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("outside the fence polygon"), "{e}");
    // A plan's fence reaching beyond the vehicle's is refused; nothing changes.
    let mut wide = fence(300.0);
    wide.polygon.clear();
    let e = set_fence
        .call(&Some(wide), STEP)
        .await
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(
            "the plan's fence circle (300 m around its home) reaches outside the vehicle's fence"
        ),
        "{e}"
    );
    // A narrower one is in force on top of the vehicle's.
    let mut narrow = fence(60.0);
    narrow.polygon.clear();
    let reply = set_fence.call(&Some(narrow), STEP).await.expect("narrower");
    assert!(reply.contains("uploaded to the autopilot"), "{reply}");
    let e = g
        .push
        .call(&vec![wp_at(1, at(100.0, 0.0))], STEP)
        .await
        .unwrap_err()
        .to_string();
    assert!(e.contains("(fence: 60 m)"), "{e}");
    assert!(
        sim.log_events("fence_uploaded")
            .iter()
            .all(|r| r["vertices"] == 4),
        "the vehicle's polygon was taken down: {:?}",
        sim.log_events("fence_uploaded")
    );
    // With the fence on board the rover starts.
    g.push_all(&zigzag(4, 10.0)).await;
    g.request(FlightState::WaypointNavigation)
        .await
        .expect("navigation with the fence on board");
    // The autopilot enforces the fence in force: narrowed under the moving rover, it breaches.
    sim.wait_log("item_reached", STEP, "the rover does not drive", |r| {
        r.len() >= 2
    })
    .await;
    let mut tight = fence(15.0);
    tight.polygon.clear();
    set_fence
        .call(&Some(tight), STEP)
        .await
        .expect("a tighter fence");
    let breach = loop {
        let f = tokio::time::timeout(STEP, failsafes.recv())
            .await
            .expect("a breach the autopilot reports")
            .expect("failsafe");
        if f.value.kind == FailsafeKind::Fence && f.value.action == "autopilot" {
            break f.value;
        }
    };
    assert!(breach.text.contains("Fence breached"), "{breach:?}");
    assert!(!sim.log_events("fence_breached").is_empty());

    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}

fn wp_at(seq: u64, (lat, lon): (f64, f64)) -> Waypoint {
    Waypoint {
        seq,
        lat,
        lon,
        ..zigzag(1, 10.0)[0].clone()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_vehicle_fence_is_on_ardupilot_before_start_and_plans_only_narrow_it() {
    tokio::time::timeout(Duration::from_secs(120), vehicle_fence_on("ardupilot"))
        .await
        .expect("the vehicle fence test ran past its bound");
}

/// The same on PX4: the fence goes as the FENCE transfer (the polygon and the circle as an
/// inclusion item) with GF_ACTION, and mavsim's PX4 vehicle takes it.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_vehicle_fence_is_on_px4_before_start_and_plans_only_narrow_it() {
    tokio::time::timeout(Duration::from_secs(120), vehicle_fence_on("px4"))
        .await
        .expect("the vehicle fence test ran past its bound");
}
