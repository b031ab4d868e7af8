//! The `fmo` binary over HTTP against real `mavsim` and `vas` processes: only the VAS's allowed
//! transitions are offered, a click changes the state, and manual control (as the page posts
//! it) drives the rover forward; releasing the dead-man stops it.

mod common;

use std::time::Duration;

use common::*;

fn rover1(s: &serde_json::Value) -> &serde_json::Value {
    vehicle(s, "rover1").expect("rover1")
}

fn pos(s: &serde_json::Value) -> (f64, f64, f64, f64) {
    let p = &rover1(s)["position"]["value"];
    (
        p["lat"].as_f64().unwrap(),
        p["lon"].as_f64().unwrap(),
        p["heading"].as_f64().unwrap(),
        p["speed"].as_f64().unwrap(),
    )
}

/// Metres north and east from `a` to `b` (flat earth: metres apart).
fn ne(a: (f64, f64), b: (f64, f64)) -> (f64, f64) {
    let r = 6_371_000.0_f64;
    (
        (b.0 - a.0).to_radians() * r,
        (b.1 - a.1).to_radians() * r * a.0.to_radians().cos(),
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn transitions_and_manual_control_on_mavsim() {
    build_flight_bins();
    tokio::time::timeout(Duration::from_secs(240), scenario())
        .await
        .expect("scenario timed out");
}

async fn scenario() {
    let domain = unique_domain("fmo-sim");
    let (sim, vas) = rover(&domain, 2.0).await;
    let fmo = Station::start(
        env!("CARGO_BIN_EXE_fmo"),
        "FMO_URL",
        &["--domain", &domain, "--vas", "rover1/vas"],
    )
    .await;

    let s = fmo
        .wait_state("PARKING with its transitions", |s| {
            vehicle(s, "rover1").is_some_and(|v| {
                v["flight_state"]["value"] == "PARKING"
                    && v["allowed"]["current"] == true
                    && v["position"].is_object()
            })
        })
        .await;
    let offered: Vec<String> = rover1(&s)["allowed"]["states"]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_str().unwrap().to_owned())
        .collect();
    assert!(
        offered.contains(&"MANUAL_NAVIGATION".to_owned()),
        "{offered:?}"
    );
    for never in ["PARKING", "TAKE_OFF", "LANDING", "CONFIGURE_CHECK"] {
        assert!(
            !offered.contains(&never.to_owned()),
            "{never} offered: {offered:?}"
        );
    }

    // "Click" MANUAL_NAVIGATION: confirmed, the state changes, new transitions are offered.
    let (status, body) = fmo
        .post(
            "/api/change_state",
            serde_json::json!({"to": "MANUAL_NAVIGATION", "vehicle": "rover1/vas"}),
        )
        .await;
    assert_eq!(status, 202, "{body}");
    let id = body["id"].as_u64().unwrap();
    let s = fmo
        .wait_state("MANUAL_NAVIGATION confirmed and current", |s| {
            let done = command(s, id).is_some_and(|c| c["status"] != "pending");
            done && rover1(s)["flight_state"]["value"] == "MANUAL_NAVIGATION"
                && rover1(s)["allowed"]["current"] == true
        })
        .await;
    let c = command(&s, id).expect("the command is listed");
    assert_eq!(c["status"], "ok", "{c:#}");
    assert!(rover1(&s)["allowed"]["states"]
        .as_array()
        .unwrap()
        .contains(&serde_json::json!("PARKING")));

    // Drive forward with the keyboard's throttle (as the page posts it at 20 Hz).
    let (lat0, lon0, hdg0, _) = pos(&s);
    let t = tokio::time::Instant::now();
    while t.elapsed() < Duration::from_secs(4) {
        fmo.post(
            "/api/manual",
            serde_json::json!({"throttle": 0.6, "deadman": true, "source": "keyboard"}),
        )
        .await;
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let s = fmo.get_json("/api/state").await;
    let (lat1, lon1, _, _) = pos(&s);
    let (n, e) = ne((lat0, lon0), (lat1, lon1));
    let along = n * hdg0.to_radians().cos() + e * hdg0.to_radians().sin();
    assert!(
        (n * n + e * e).sqrt() > 1.0,
        "the rover did not move: {n:.2} m N, {e:.2} m E"
    );
    assert!(
        along > 0.5,
        "moved {along:.2} m along heading {hdg0}: not forward ({n:.2} N, {e:.2} E)"
    );

    // Release the dead-man: the rover stops.
    fmo.post("/api/manual", serde_json::json!({"deadman": false}))
        .await;
    let s = fmo
        .wait_state("the rover stopped", |s| {
            rover1(s)["position"]["value"]["speed"]
                .as_f64()
                .is_some_and(|v| v < 0.1)
        })
        .await;
    let stopped = pos(&s);
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let later = pos(&fmo.get_json("/api/state").await);
    let (n, e) = ne((stopped.0, stopped.1), (later.0, later.1));
    assert!(
        (n * n + e * e).sqrt() < 0.5,
        "still moving after release: {n:.2} N {e:.2} E"
    );

    fmo.kill().await;
    vas.kill().await;
    sim.kill().await;
}
