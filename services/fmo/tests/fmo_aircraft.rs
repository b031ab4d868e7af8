//! The pilot flies an aircraft from the FMo against real `mavsim` and `vas` processes: DIRECTED
//! (altitude, speed, bearing) is sent from the station, the VAS's refusals reach the command
//! list with their reasons, and an accepted target is flown.

mod common;

use std::time::Duration;

use common::*;

fn copter1(s: &serde_json::Value) -> &serde_json::Value {
    vehicle(s, "copter1").expect("copter1")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_pilot_flies_a_copter_directed_from_the_fmo_and_refusals_say_why() {
    build_flight_bins();
    tokio::time::timeout(Duration::from_secs(180), scenario())
        .await
        .expect("scenario timed out");
}

/// Posts `command` and waits for the VAS's answer; returns the command's entry.
async fn send(fmo: &Station, command: serde_json::Value) -> serde_json::Value {
    let (status, body) = fmo
        .post(
            "/api/command",
            serde_json::json!({"command": command, "vehicle": "copter1/vas"}),
        )
        .await;
    assert_eq!(status, 202, "{body}");
    let id = body["id"].as_u64().expect("an id");
    let s = fmo
        .wait_state("the VAS's answer", |s| {
            command_of(s, id).is_some_and(|c| c["status"] != "pending")
        })
        .await;
    command_of(&s, id).cloned().expect("listed")
}

fn command_of(s: &serde_json::Value, id: u64) -> Option<&serde_json::Value> {
    common::command(s, id)
}

async fn scenario() {
    let domain = unique_domain("fmo-copter");
    let (sim, vas) = vehicle_named(&domain, 5.0, "copter1", "copter").await;
    let fmo = Station::start(
        env!("CARGO_BIN_EXE_fmo"),
        "FMO_URL",
        &["--domain", &domain, "--vas", "copter1/vas"],
    )
    .await;
    fmo.wait_state("PARKING", |s| {
        vehicle(s, "copter1").is_some_and(|v| v["flight_state"]["value"] == "PARKING")
    })
    .await;
    let directed = |alt: f64, speed: f64, bearing: f64| serde_json::json!({"DIRECTED": {"alt": alt, "speed": speed, "bearing": bearing}});
    // On the ground: refused, and the reason says a take-off comes first.
    let c = send(&fmo, directed(20.0, 5.0, 90.0)).await;
    assert_eq!(c["status"], "failed", "{c}");
    assert!(
        c["detail"].as_str().is_some_and(|d| d.contains("TAKE_OFF")),
        "{c}"
    );
    // Not a command at all: refused by the station, naming the forms.
    let (status, body) = fmo
        .post("/api/command", serde_json::json!({"command": "FLY"}))
        .await;
    assert_eq!(status, 400, "{body}");
    assert!(
        body["error"]
            .as_str()
            .is_some_and(|e| e.contains("DIRECTED")),
        "{body}"
    );

    let (status, body) = fmo
        .post(
            "/api/change_state",
            serde_json::json!({"to": "TAKE_OFF", "vehicle": "copter1/vas"}),
        )
        .await;
    assert_eq!(status, 202, "{body}");
    fmo.wait_state("climbed", |s| {
        copter1(s)["position"]["value"]["alt_rel"]
            .as_f64()
            .is_some_and(|a| a > 8.0)
    })
    .await;
    // A target that cannot be flown: the VAS's reason.
    let c = send(&fmo, directed(20.0, 0.0, 90.0)).await;
    assert_eq!(c["status"], "failed", "{c}");
    assert!(
        c["detail"].as_str().is_some_and(|d| d.contains("speed")),
        "{c}"
    );
    // East at 20 m: flown.
    let c = send(&fmo, directed(20.0, 5.0, 90.0)).await;
    assert_eq!(c["status"], "ok", "{c}");
    assert!(
        c["what"]
            .as_str()
            .is_some_and(|w| w.contains("DIRECTED alt 20 m")),
        "{c}"
    );
    let start = fmo.get_json("/api/state").await;
    let lon0 = copter1(&start)["position"]["value"]["lon"]
        .as_f64()
        .unwrap();
    fmo.wait_state("flying east at 20 m in DIRECTED", |s| {
        let v = copter1(s);
        let p = &v["position"]["value"];
        v["flight_state"]["value"] == "DIRECTED"
            && p["lon"].as_f64().is_some_and(|lon| lon > lon0 + 0.0003)
            && p["alt_rel"]
                .as_f64()
                .is_some_and(|a| (a - 20.0).abs() < 2.0)
    })
    .await;
    fmo.kill().await;
    vas.kill().await;
    sim.kill().await;
}
