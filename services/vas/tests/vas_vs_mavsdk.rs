//! Conformance: the `vas` binary flying a vehicle whose MAVLink side is MAVSDK's server
//! plugins (`tests/python/mavsdk_vehicle.py`), an implementation not written here, with its
//! own conventions: a generic autopilot with PX4 custom modes, item 0 ordinary, no partial
//! writes, the current item reset to 0 by every upload.
//!
//! The 50-waypoint plan completes through the rolling queue with 0 skipped, 0 repeated and 0
//! backtracks as the vehicle reports them. Skipped, saying so, only where `python3` is absent.

mod common;

use common::mavsdk::{python, score, MavsdkVehicle};
use common::*;
use usal_types::{FlightState, QueueStatus};

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fifty_waypoints_on_a_mavsdk_vehicle() {
    let Some(py) = tokio::task::spawn_blocking(python)
        .await
        .expect("finding python")
    else {
        return;
    };
    let run = async {
        // 2x: a 10 m leg in 1 s of wall time, so a loaded machine does not turn the short window
        // between an upload (current item reset to 0) and its restoration into a skip.
        let mut vehicle = MavsdkVehicle::start(&py, 2.0, STEP).await;
        let domain = unique_domain("mavsdk");
        let vas = VasProc::start(
            &format!("udpout:127.0.0.1:{}", vehicle.port),
            &domain,
            &["--queue-size", "5"],
        );
        let g = Ground::open(&domain).await;
        let queue = g
            .svc
            .subscribe_variable::<QueueStatus>("rover1/vas/queue")
            .unwrap();
        g.wait_state(FlightState::Parking, STEP).await;
        let wps = zigzag(50, 10.0);
        g.fly_in_order(&wps, "mavsdk").await;

        let events = vehicle.drain();
        let plan: Vec<(f64, f64)> = wps.iter().map(|w| (w.lat, w.lon)).collect();
        let flown = score(&events, &plan);
        if flown.reached != (0..50).collect::<Vec<_>>() || flown.backtracks > 0 {
            // What the vehicle said, to tell a skip from a turn back.
            for e in &events {
                eprintln!("vehicle: {e}");
            }
        }
        assert_eq!(flown.reached, (0..50).collect::<Vec<_>>(), "{flown:?}");
        assert_eq!(
            (flown.skipped, flown.repeated, flown.backtracks),
            (0, 0, 0),
            "skipped, repeated, backtracks as the vehicle reports them: {flown:?}"
        );
        assert!(
            events
                .iter()
                .any(|e| e["event"] == "current" && e["seq"] == 0),
            "MAVSDK reset the current item after an upload (so restoring it was tested)"
        );
        assert_eq!(latest_queue_status(&queue).backtracks, 0);
        vas.kill().await;
        vehicle.kill().await;
        g.node.shutdown().await;
    };
    tokio::time::timeout(STEP * 9, run)
        .await
        .expect("the MAVSDK flight is bounded");
}
