//! The PX4 autopilot layer against mavsim `--autopilot px4`: DIRECTED by MAV_CMD_DO_REPOSITION
//! through the `vas` binary, and [`Px4`]'s `direct_to` sending the vehicle to a point (the
//! library over a real UDP link to the mavsim process).
//!
//! MAVSDK's server plugins have no DO_REPOSITION (its action server answers arming, take-off,
//! landing, return and mode changes only), so DIRECTED is not driven on the MAVSDK vehicle.

mod common;

use common::*;
use usal_types::{FlightState, ManualControl};
use vas::apl::mavlink::{MavlinkApConfig, MavlinkAutopilot};
use vas::apl::{ApEvent, IAutopilot};
use vas::mavlink_cm::{AutopilotFamily, ManagerConfig};

/// Metres between two (lat, lon).
fn dist(a: (f64, f64), b: (f64, f64)) -> f64 {
    let m = 111_319.49;
    let dn = (a.0 - b.0) * m;
    let de = (a.1 - b.1) * m * a.0.to_radians().cos();
    dn.hypot(de)
}

/// Waits until mavsim's log holds a record of `event` satisfying `f`.
async fn wait_log(sim: &Sim, event: &str, f: impl Fn(&serde_json::Value) -> bool) {
    let what = format!("no {event} in mavsim's log");
    sim.wait_log(event, STEP, &what, |records| records.iter().any(&f))
        .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn directed_on_the_px4_profile_is_a_reposition_where_the_vehicle_is() {
    tokio::time::timeout(STEP * 6, async {
        let dir = tempfile::tempdir().unwrap();
        let sim = Sim::start_with(
            "127.0.0.1:0",
            20.0,
            &dir.path().join("sim.jsonl"),
            &["--autopilot", "px4"],
        )
        .await;
        // The PX4 APL by configuration (`autopilot="px4"`), not only by the heartbeat.
        let cfg = dir.path().join("vas.xml");
        std::fs::write(&cfg, r#"<vas autopilot="px4"/>"#).unwrap();
        let domain = unique_domain("px4-directed");
        let vas = VasProc::start(
            &format!("udpout:{}", sim.addr),
            &domain,
            &["--config", cfg.to_str().unwrap(), "--queue-size", "5"],
        );
        let g = Ground::open(&domain).await;
        g.wait_state(FlightState::Parking, STEP).await;
        let wps = zigzag(12, 10.0);
        g.push_all(&wps).await;
        let reply = g.request(FlightState::WaypointNavigation).await;
        assert!(reply.is_ok(), "{reply:?}");
        for want in 0..3u64 {
            let r = tokio::time::timeout(STEP, g.reached.recv())
                .await
                .expect("waypoint reached in time")
                .expect("waypoint_reached");
            assert_eq!(r.value.seq, want);
        }
        // The mission was started with MAV_CMD_MISSION_START (AUTO.MISSION from slot 1).
        assert!(sim
            .log_events("mode_changed")
            .iter()
            .any(|e| e["name"] == "AUTO"));

        let reply = g.request(FlightState::Directed).await;
        assert!(reply.is_ok(), "{reply:?}");
        wait_log(&sim, "repositioned", |_| true).await;
        wait_log(&sim, "mode_changed", |e| e["name"] == "HOLD").await;
        // The vehicle stops where it was and holds there: no waypoint is reached any more.
        wait_log(&sim, "reposition_reached", |_| true).await;
        let reached_before = sim.log_events("item_reached").len();
        g.wait_state(FlightState::Directed, STEP).await;
        let held = sim.log_events("reposition_reached")[0].clone();
        let held = (held["lat"].as_f64().unwrap(), held["lon"].as_f64().unwrap());
        let rep = sim.log_events("repositioned")[0].clone();
        let rep = (rep["lat"].as_f64().unwrap(), rep["lon"].as_f64().unwrap());
        assert!(dist(held, rep) < 0.01, "held where it was sent");
        assert_eq!(sim.log_events("item_reached").len(), reached_before);
        vas.kill().await;
        sim.kill().await;
        g.node.shutdown().await;
    })
    .await
    .expect("DIRECTED on px4 bounded");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_px4_layer_directs_the_vehicle_to_a_point_and_it_holds_there() {
    tokio::time::timeout(STEP * 6, async {
        let dir = tempfile::tempdir().unwrap();
        let sim = Sim::start_with(
            "127.0.0.1:0",
            20.0,
            &dir.path().join("sim.jsonl"),
            &["--autopilot", "px4"],
        )
        .await;
        let cfg = MavlinkApConfig {
            manager: ManagerConfig {
                connect_wait: STEP,
                family: Some(AutopilotFamily::Px4),
                ..ManagerConfig::default()
            },
            ..MavlinkApConfig::default()
        };
        let px4 = MavlinkAutopilot::open(&format!("udpout:{}", sim.addr), cfg)
            .await
            .expect("open");
        let mut events = px4.events();
        px4.listen_ap().await.expect("listen_ap");
        // Not in DIRECTED yet: refused.
        let early = px4.direct_to(HOME.0, HOME.1, f32::NAN, 0.0).await;
        assert!(early.is_err(), "{early:?}");
        // Armed by MANUAL_NAVIGATION (sticks centred), then DIRECTED.
        px4.change_state(FlightState::ManualNavigation)
            .await
            .expect("manual navigation");
        px4.manual_navigation(Some(ManualControl::default()))
            .await
            .expect("sticks");
        px4.change_state(FlightState::Directed)
            .await
            .expect("directed");
        assert_eq!(px4.status().mode, "HOLD");
        // 40 m north-east of home, at 4 m/s.
        let m = 1.0 / 111_319.49;
        let goal = (
            HOME.0 + 30.0 * m,
            HOME.1 + 25.0 * m / HOME.0.to_radians().cos(),
        );
        px4.direct_to(goal.0, goal.1, f32::NAN, 4.0)
            .await
            .expect("direct_to");
        wait_log(&sim, "reposition_reached", |e| {
            dist(
                (e["lat"].as_f64().unwrap(), e["lon"].as_f64().unwrap()),
                goal,
            ) < 0.5
        })
        .await;
        // The VAS's own telemetry shows it there.
        let there = tokio::time::timeout(STEP, async {
            loop {
                match events.recv().await {
                    Ok(ApEvent::Position(p)) if dist((p.lat, p.lon), goal) < 3.0 => return,
                    Ok(_) | Err(tokio::sync::broadcast::error::RecvError::Lagged(_)) => {}
                    Err(e) => panic!("events: {e}"),
                }
            }
        })
        .await;
        assert!(there.is_ok(), "no position near the goal");
        assert_eq!(px4.status().mode, "HOLD", "still directed, holding");
        px4.shutdown().await;
        sim.kill().await;
    })
    .await
    .expect("direct_to bounded");
}
