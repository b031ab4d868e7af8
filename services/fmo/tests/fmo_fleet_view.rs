//! The stations' fleet view through the HTTP API the page uses, on real processes: two rovers
//! (`mavsim` + `vas`, `rover1` and `rover2`), a `fleet` service running a fleet plan over both,
//! and an `fmo` and an `fpmo` following them. Both stations show both vehicles with their state
//! and position; a vehicle selected on the FMo is paused and resumed through the fleet service;
//! bad commands are refused with the reason.

mod common;

use std::time::Duration;

use common::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_stations_show_the_whole_fleet_and_command_a_selected_vehicle() {
    build_flight_bins();
    tokio::time::timeout(Duration::from_secs(240), scenario())
        .await
        .expect("scenario timed out");
}

async fn scenario() {
    let domain = unique_domain("fleet-view");
    let (_sim1, _vas1) = rover_named(&domain, 2.0, "rover1").await;
    let (_sim2, _vas2) = rover_named(&domain, 2.0, "rover2").await;
    let dir = tempfile::tempdir().unwrap();
    let plan = dir.path().join("fleet.xml");
    // A plan that only waits: the vehicles stay where they are while the stations look.
    std::fs::write(
        &plan,
        r#"<fleetPlan name="view">
  <vehicle id="scout" prefix="rover1" priority="2"/>
  <vehicle id="helper" prefix="rover2"/>
  <obstacles>
    <obstacle name="shed" height="6">
      <pt lat="41.2760" lon="1.9883"/><pt lat="41.2760" lon="1.9885"/><pt lat="41.2762" lon="1.9884"/>
    </obstacle>
  </obstacles>
  <seq><wait event="detection"/></seq>
</fleetPlan>"#,
    )
    .unwrap();
    let _fleet = fleet_service(&plan, &domain).await;
    let fmo = Station::start(env!("CARGO_BIN_EXE_fmo"), "FMO_URL", &["--domain", &domain]).await;
    let fpmo = Station::start(
        workspace_bin("fpmo").to_str().unwrap(),
        "FPMO_URL",
        &["--domain", &domain],
    )
    .await;

    // Every vehicle, with its state and position, on both stations.
    for station in [&fmo, &fpmo] {
        let j = station
            .wait_fleet("both vehicles placed", |s| {
                s["vehicles"].as_array().is_some_and(|v| {
                    v.len() == 2
                        && v.iter()
                            .all(|v| v["position"].is_array() && v["state"].is_string())
                })
            })
            .await;
        assert_eq!(j["fleets"][0]["service"], "gcs/fleet", "{j}");
        let s = &j["fleets"][0]["status"];
        assert_eq!(s["plan"], "view");
        assert_eq!(s["vehicles"][0]["id"], "scout");
        assert_eq!(s["vehicles"][1]["prefix"], "rover2");
        assert_eq!(s["obstacles"][0]["name"], "shed", "{s}");
        let lat = s["vehicles"][0]["position"][0].as_f64().unwrap();
        assert!((lat - HOME.0).abs() < 0.001, "{s}");
        let (status, page) = station.get("/fleet").await;
        assert_eq!(status, 200);
        assert!(page.contains("USAL fleet") && page.contains("/api/fleet"));
        // The token guards the fleet API like the rest.
        let (status, _) = request(&station.addr, "GET", "/api/fleet", None).await;
        assert!(status == 401 || status == 403, "{status}");
    }

    // The fleet view draws the obstacle among the vehicles.
    match Browser::start().await {
        Some(browser) => {
            browser
                .goto(&format!("http://{}/fleet?token={}", fmo.addr, fmo.token))
                .await;
            browser
                .wait_for(
                    "the shed on the fleet map",
                    "const o = document.querySelector('#map [data-obstacle=shed]'); \
                     return !!o && o.textContent.includes('shed 6 m');",
                )
                .await;
            browser.close().await;
        }
        None => test_support::tool_missing("chromium/chromedriver", "run .ci/install-chromium"),
    }

    // The selected vehicle, paused and resumed from the FMo.
    let (status, answer) = fmo
        .post(
            "/api/fleet/command",
            serde_json::json!({"vehicle": "scout", "action": "pause"}),
        )
        .await;
    assert_eq!((status, &answer["answer"]), (200, &"scout paused".into()));
    // Seen by the other station too.
    fpmo.wait_fleet("scout paused", |s| s["vehicles"][0]["paused"] == true)
        .await;
    let (status, answer) = fmo
        .post(
            "/api/fleet/command",
            serde_json::json!({"vehicle": "scout", "action": "resume", "fleet": "gcs/fleet"}),
        )
        .await;
    assert_eq!((status, &answer["answer"]), (200, &"scout resumed".into()));
    fmo.wait_fleet("scout resumed", |s| s["vehicles"][0]["paused"] == false)
        .await;

    let (status, answer) = fmo
        .post(
            "/api/fleet/command",
            serde_json::json!({"vehicle": "nobody", "action": "pause"}),
        )
        .await;
    assert_eq!(status, 404, "{answer}");
    assert!(answer["error"].as_str().unwrap().contains("nobody"));
    let (status, answer) = fmo
        .post(
            "/api/fleet/command",
            serde_json::json!({"vehicle": "scout", "action": "jump"}),
        )
        .await;
    assert_eq!(status, 400, "{answer}");
    let (status, _) = fmo
        .post(
            "/api/fleet/command",
            serde_json::json!({"vehicle": "scout", "action": "pause", "fleet": "elsewhere/fleet"}),
        )
        .await;
    assert_eq!(status, 404);
    fmo.kill().await;
    fpmo.kill().await;
}
