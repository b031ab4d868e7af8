//! Manual control reaches one vehicle only: two rovers (two `mavsim` + `vas` processes, `rover1`
//! and `rover2`) both in MANUAL_NAVIGATION, one `fmo` following both. Driving `rover1` moves
//! `rover1` and not `rover2`; switching to `rover2` with the dead-man still held stops `rover1`
//! and does not drive `rover2` until the dead-man is released and held again.

mod common;

use std::time::Duration;

use common::*;

fn at(s: &serde_json::Value, label: &str) -> (f64, f64) {
    let p = &vehicle(s, label).expect("vehicle")["position"]["value"];
    (p["lat"].as_f64().unwrap(), p["lon"].as_f64().unwrap())
}

/// Metres between two positions (flat earth: they are metres apart).
fn dist(a: (f64, f64), b: (f64, f64)) -> f64 {
    let r = 6_371_000.0_f64;
    let n = (b.0 - a.0).to_radians() * r;
    let e = (b.1 - a.1).to_radians() * r * a.0.to_radians().cos();
    (n * n + e * e).sqrt()
}

/// Posts held sticks (throttle forward) as the page does, at 20 Hz for `how_long`.
async fn drive(fmo: &Station, how_long: Duration) {
    let t = tokio::time::Instant::now();
    while t.elapsed() < how_long {
        let (status, _) = fmo
            .post(
                "/api/manual",
                serde_json::json!({"throttle": 0.6, "deadman": true, "source": "keyboard"}),
            )
            .await;
        assert_eq!(status, 204);
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn manual_control_drives_the_commanded_vehicle_only() {
    build_flight_bins();
    tokio::time::timeout(Duration::from_secs(240), scenario())
        .await
        .expect("scenario timed out");
}

async fn scenario() {
    let domain = unique_domain("fmo-fleet");
    let (sim1, vas1) = rover_named(&domain, 2.0, "rover1").await;
    let (sim2, vas2) = rover_named(&domain, 2.0, "rover2").await;
    let fmo = Station::start(
        env!("CARGO_BIN_EXE_fmo"),
        "FMO_URL",
        &["--domain", &domain, "--vas", "*/vas"],
    )
    .await;

    // Both rovers in MANUAL_NAVIGATION: both would obey sticks addressed to them.
    for ns in ["rover1", "rover2"] {
        fmo.wait_state(&format!("{ns} PARKING"), |s| {
            vehicle(s, ns).is_some_and(|v| {
                v["flight_state"]["value"] == "PARKING" && v["position"].is_object()
            })
        })
        .await;
        let (status, body) = fmo
            .post(
                "/api/change_state",
                serde_json::json!({"to": "MANUAL_NAVIGATION", "vehicle": format!("{ns}/vas")}),
            )
            .await;
        assert_eq!(status, 202, "{body}");
        fmo.wait_state(&format!("{ns} in MANUAL_NAVIGATION"), |s| {
            vehicle(s, ns).is_some_and(|v| v["flight_state"]["value"] == "MANUAL_NAVIGATION")
        })
        .await;
    }
    let (status, _) = fmo
        .post("/api/select", serde_json::json!({"vehicle": "rover1/vas"}))
        .await;
    assert_eq!(status, 204);

    // Drive rover1: it moves, rover2 does not.
    let s0 = fmo.get_json("/api/state").await;
    drive(&fmo, Duration::from_secs(4)).await;
    let s1 = fmo.get_json("/api/state").await;
    assert_eq!(s1["manual"]["target"], "rover1");
    let moved1 = dist(at(&s0, "rover1"), at(&s1, "rover1"));
    let moved2 = dist(at(&s0, "rover2"), at(&s1, "rover2"));
    assert!(moved1 > 1.0, "rover1 did not move: {moved1:.2} m");
    assert!(
        moved2 < 0.3,
        "rover2 obeyed sticks addressed to rover1: moved {moved2:.2} m"
    );

    // Switch to rover2 with the dead-man still held: rover1 stops, rover2 waits for a re-arm.
    let (status, _) = fmo
        .post("/api/select", serde_json::json!({"vehicle": "rover2/vas"}))
        .await;
    assert_eq!(status, 204);
    let s2 = fmo.get_json("/api/state").await;
    drive(&fmo, Duration::from_secs(3)).await;
    let s3 = fmo
        .wait_state("rover1 stopped", |s| {
            vehicle(s, "rover1").is_some_and(|v| {
                v["position"]["value"]["speed"]
                    .as_f64()
                    .is_some_and(|v| v < 0.1)
            })
        })
        .await;
    assert_eq!(s3["manual"]["rearm"], true, "{:#}", s3["manual"]);
    let moved2 = dist(at(&s2, "rover2"), at(&s3, "rover2"));
    assert!(
        moved2 < 0.3,
        "a held dead-man jumped to rover2: moved {moved2:.2} m"
    );

    // Release, hold again: now rover2 moves and rover1 stays put.
    fmo.post("/api/manual", serde_json::json!({"deadman": false}))
        .await;
    let s4 = fmo.get_json("/api/state").await;
    drive(&fmo, Duration::from_secs(4)).await;
    let s5 = fmo.get_json("/api/state").await;
    assert_eq!(s5["manual"]["target"], "rover2");
    let moved1 = dist(at(&s4, "rover1"), at(&s5, "rover1"));
    let moved2 = dist(at(&s4, "rover2"), at(&s5, "rover2"));
    assert!(moved2 > 1.0, "rover2 did not move: {moved2:.2} m");
    assert!(
        moved1 < 0.3,
        "rover1 obeyed sticks addressed to rover2: moved {moved1:.2} m"
    );

    fmo.post("/api/manual", serde_json::json!({"deadman": false}))
        .await;
    fmo.kill().await;
    for p in [vas1, vas2, sim1, sim2] {
        p.kill().await;
    }
}
