//! The commanded vehicle's camera in the FMo, on real processes: a rover (`mavsim --camera`,
//! `vas`, `fpma`) with a `camera` service, a `fleet` service sending it to the points to
//! visit, and an `fmo`. The page shows the live picture (a frame under 2 s old); a point
//! clicked on it is put on the ground with the frame's pose and reaches the investigator's
//! plan, which flies there.

mod common;

use std::time::Duration;

use common::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_fmo_shows_the_camera_and_a_point_clicked_on_it_reaches_the_investigators_plan() {
    build_flight_bins();
    tokio::time::timeout(Duration::from_secs(240), scenario())
        .await
        .expect("scenario timed out");
}

async fn scenario() {
    let domain = unique_domain("camera");
    let camera_at = format!("127.0.0.1:{}", test_support::free_tcp_port());
    // A wide lens (150°): on the ground, the picture covers ~15 m across.
    let sim_args: Vec<String> = [
        "--camera",
        "160x120",
        "--camera-fps",
        "10",
        "--camera-hfov",
        "150",
        "--camera-listen",
        &camera_at,
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    let (_sim, _vas) = vehicle_with(&domain, 4.0, "rover1", "rover", &sim_args).await;
    let dir = tempfile::tempdir().unwrap();
    let _fpma = fpma_rover1(&domain, dir.path()).await;
    let camera_args: Vec<String> = [
        "--source",
        &camera_at,
        "--domain",
        &domain,
        "--namespace",
        "rover1",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    let _camera = Proc::start(&workspace_bin("camera"), &camera_args, false).await;
    let plan = dir.path().join("fleet.xml");
    std::fs::write(
        &plan,
        r#"<fleetPlan name="camera">
  <vehicle id="scout" prefix="rover1"/>
  <variables><var name="enough" type="bool" init="false"/></variables>
  <seq><investigate vehicle="scout" until="enough" speed="3"/></seq>
</fleetPlan>"#,
    )
    .unwrap();
    let _fleet = fleet_service(&plan, &domain).await;
    let fmo = Station::start(env!("CARGO_BIN_EXE_fmo"), "FMO_URL", &["--domain", &domain]).await;
    fmo.wait_fleet("the rover placed", |s| {
        s["vehicles"][0]["position"].is_array()
    })
    .await;

    let Some(browser) = Browser::start().await else {
        test_support::tool_missing("chromium/chromedriver", "run .ci/install-chromium");
        return;
    };
    browser.goto(&fmo.url).await;
    // The live picture: shown, decoded, and from a frame under 2 s old.
    let age = browser
        .wait_for(
            "a live camera picture",
            "const i = document.getElementById('camimg'); \
             const a = Number(document.getElementById('camage').dataset.ageMs); \
             return i.style.display === 'block' && i.complete && i.naturalWidth === 160 \
               && a < 2000 ? a + 1 : 0;",
        )
        .await;
    assert!(age.as_f64().is_some_and(|a| a <= 2000.0), "{age}");
    // A click near the picture's top-left corner: ahead and to the left of the rover.
    browser
        .eval(
            "const i = document.getElementById('camimg'); const r = i.getBoundingClientRect(); \
             i.dispatchEvent(new MouseEvent('click', {clientX: r.left + r.width * 0.1, \
             clientY: r.top + r.height * 0.1, bubbles: true})); return true;",
        )
        .await;
    browser
        .wait_for(
            "the mark's answer",
            "return document.getElementById('camnote').textContent.includes('point #1 added');",
        )
        .await;
    browser.close().await;
    let cams = fmo.get_json("/api/cameras").await;
    assert_eq!(cams["cameras"][0]["camera"], "rover1/camera", "{cams}");
    assert_eq!(cams["cameras"][0]["width"], 160, "{cams}");
    // The point is on the ground where the picture showed it: a few metres from the rover,
    // not under it; it reaches the investigator's plan, which flies there.
    let s = fmo
        .wait_fleet("the marked point in the investigator's plan", |s| {
            s["vehicles"][0]["plan"] == "visit-1"
        })
        .await;
    let s = &s["fleets"][0]["status"];
    let d = &s["detections"][0];
    assert_eq!(
        (d["by"].as_str(), d["id"].as_u64()),
        (Some("operator"), Some(1)),
        "{s}"
    );
    let (lat, lon) = (d["lat"].as_f64().unwrap(), d["lon"].as_f64().unwrap());
    let k = HOME.0.to_radians().cos();
    let (north, east) = ((lat - HOME.0) * 111_319.49, (lon - HOME.1) * 111_319.49 * k);
    let dist = north.hypot(east);
    assert!((4.0..12.0).contains(&dist), "{dist} m from home: {s}");
    let route = s["vehicles"][0]["route"].as_array().expect("its route");
    let end = route.last().expect("a route");
    assert!(
        (end[0].as_f64().unwrap() - lat).abs() < 1e-6
            && (end[1].as_f64().unwrap() - lon).abs() < 1e-6,
        "the plan ends at the point: {s}"
    );
    fmo.wait_fleet("the point visited", |s| {
        s["visit_order"] == serde_json::json!([1])
    })
    .await;
    fmo.kill().await;
}
