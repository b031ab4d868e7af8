//! The same plan flown by the `vas` binary on each of mavsim's autopilot profiles: ArduPilot
//! (item 0 home, partial writes, current item kept by uploads), PX4 (PX4 custom modes, item 0
//! ordinary, no partial writes, current item reset to 0 by every upload, MISSION_CURRENT only
//! on change), generic (ArduPilot modes, PX4's mission conventions) and ArduPilot-resetting
//! (says ArduPilot, but no partial writes and the current item reset). Every waypoint is
//! reached once, in order, and the vehicle never turns back.

mod common;

use common::*;
use usal_types::{FlightState, QueueStatus};

/// Flies `n` waypoints on mavsim `--autopilot profile`; returns after checking them.
async fn fly_on(profile: &str, n: usize) {
    fly_configured(profile, n, None).await;
}

/// [`fly_on`] with the VAS's `autopilot` attribute set to `family` (else `auto`).
async fn fly_configured(profile: &str, n: usize, family: Option<&str>) {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("vas.xml");
    std::fs::write(
        &cfg,
        format!(r#"<vas autopilot="{}"/>"#, family.unwrap_or("auto")),
    )
    .unwrap();
    let sim = Sim::start_with(
        "127.0.0.1:0",
        30.0,
        &dir.path().join("sim.jsonl"),
        &["--autopilot", profile],
    )
    .await;
    let domain = unique_domain(&format!("profile-{profile}"));
    let vas = VasProc::start(
        &format!("udpout:{}", sim.addr),
        &domain,
        &["--config", cfg.to_str().unwrap(), "--queue-size", "5"],
    );
    let g = Ground::open(&domain).await;
    let queue = g
        .svc
        .subscribe_variable::<QueueStatus>("rover1/vas/queue")
        .unwrap();
    g.wait_state(FlightState::Parking, STEP).await;

    let wps = zigzag(n, 10.0);
    g.fly_in_order(&wps, profile).await;

    // What the vehicle did: every waypoint reached once, in order; item 0 (home on
    // ArduPilot, the target's copy elsewhere) never reached as anything else.
    let order: Vec<Option<usize>> = reached_points(&sim.log_events("item_reached"))
        .into_iter()
        .map(|p| which(&wps, p))
        .collect();
    let mut dedup = order.clone();
    dedup.dedup();
    assert_eq!(
        dedup,
        (0..n).map(Some).collect::<Vec<_>>(),
        "{profile}: mavsim reached every waypoint in order, nothing else; mavsim's log:\n{}",
        sim.mission_story()
    );
    let repeated = order.len() - dedup.len();
    assert!(
        repeated == 0,
        "{profile}: {repeated} waypoints reached twice in a row; mavsim's log:\n{}",
        sim.mission_story()
    );
    if profile != "ardupilot" {
        // The profile's conventions were met: uploads reset the current item, and it was
        // restored each time.
        let resets = sim
            .log_events("current_changed")
            .iter()
            .filter(|e| e["cause"] == "upload_reset")
            .count();
        assert!(resets > 0, "{profile}: no upload reset the current item");
    }
    // The VAS saw no backtrack either.
    let last = latest_queue_status(&queue);
    assert_eq!(last.backtracks, 0, "{profile}: {last:?}");
    vas.kill().await;
    sim.kill().await;
    g.node.shutdown().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn forty_waypoints_on_the_ardupilot_profile() {
    tokio::time::timeout(STEP * 12, fly_on("ardupilot", 40))
        .await
        .expect("ardupilot profile flight bounded");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn forty_waypoints_on_the_px4_profile() {
    tokio::time::timeout(STEP * 12, fly_on("px4", 40))
        .await
        .expect("px4 profile flight bounded");
}

/// The PX4 APL (`autopilot="px4"`), not only the heartbeat's choice: PX4's modes, the
/// mission started with MAV_CMD_MISSION_START.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn thirty_waypoints_on_the_px4_profile_with_the_px4_layer() {
    tokio::time::timeout(STEP * 10, fly_configured("px4", 30, Some("px4")))
        .await
        .expect("px4 layer flight bounded");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn forty_waypoints_on_the_generic_profile() {
    tokio::time::timeout(STEP * 12, fly_on("generic", 40))
        .await
        .expect("generic profile flight bounded");
}

/// A vehicle that says it is ArduPilot (item 0 home) but resets its current item after every
/// whole upload and answers no partial write: the VAS finds the partial writes missing, lays
/// each whole window out from the target, so every reset lands on it, and the vehicle never
/// heads for home or a waypoint it has passed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn thirty_waypoints_on_a_vehicle_that_says_ardupilot_but_resets_on_upload() {
    tokio::time::timeout(STEP * 12, fly_on("ardupilot-resetting", 30))
        .await
        .expect("ardupilot-resetting flight bounded");
}
