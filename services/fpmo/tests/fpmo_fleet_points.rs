//! The operator edits the points an investigator visits, mid-flight, from the FPMo's fleet view,
//! on real processes: a rover (`mavsim`, `vas`, `fpma`) investigating for a `fleet` service, and an
//! `fpmo`. Paused from the FPMo, the rover waits while the operator adds points (one on the map
//! with a click), refuses one inside the shed, puts two in order and deletes two; resumed, it
//! visits its first point, then the operator's two in their order, and never the deleted ones.

#[path = "../../fmo/tests/common/mod.rs"]
mod common;

use std::time::Duration;

use common::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_operator_adds_deletes_and_orders_points_and_pauses_the_investigator_from_the_fpmo() {
    build_flight_bins();
    tokio::time::timeout(Duration::from_secs(240), scenario())
        .await
        .expect("scenario timed out");
}

/// `(lat, lon)` `north` and `east` metres from home.
fn at(north: f64, east: f64) -> (f64, f64) {
    let k = HOME.0.to_radians().cos();
    (
        HOME.0 + north / 111_319.49,
        HOME.1 + east / (111_319.49 * k),
    )
}

/// The operator's points of a fleet status: `(id, visited, deleted)`.
fn operator_points(s: &serde_json::Value) -> Vec<(u64, bool, bool)> {
    s["detections"]
        .as_array()
        .into_iter()
        .flatten()
        .filter(|d| d["by"] == "operator")
        .map(|d| {
            (
                d["id"].as_u64().unwrap_or(0),
                !d["visited"].is_null(),
                d["deleted"] == true,
            )
        })
        .collect()
}

async fn add(fpmo: &Station, (lat, lon): (f64, f64)) -> (u16, serde_json::Value) {
    fpmo.post(
        "/api/fleet/points",
        serde_json::json!({"edit": {"Add": {"lat": lat, "lon": lon}}}),
    )
    .await
}

async fn scenario() {
    let domain = unique_domain("fleet-points");
    let (_sim, _vas) = rover_named(&domain, 5.0, "rover1").await;
    let dir = tempfile::tempdir().unwrap();
    let _fpma = fpma_rover1(&domain, dir.path()).await;
    let plan = dir.path().join("fleet.xml");
    let shed = [
        at(-80.0, -10.0),
        at(-80.0, 10.0),
        at(-100.0, 10.0),
        at(-100.0, -10.0),
    ];
    let pts: Vec<String> = shed
        .iter()
        .map(|(la, lo)| format!(r#"<pt lat="{la:.7}" lon="{lo:.7}"/>"#))
        .collect();
    std::fs::write(
        &plan,
        format!(
            r#"<fleetPlan name="points">
  <vehicle id="helper" prefix="rover1"/>
  <variables><var name="enough" type="bool" init="false"/></variables>
  <obstacles><obstacle name="shed" height="6">{}</obstacle></obstacles>
  <seq><investigate vehicle="helper" until="enough" speed="4"/></seq>
</fleetPlan>"#,
            pts.join("")
        ),
    )
    .unwrap();
    let _fleet = fleet_service(&plan, &domain).await;
    let fpmo = Station::start(
        workspace_bin("fpmo").to_str().unwrap(),
        "FPMO_URL",
        &["--domain", &domain],
    )
    .await;
    fpmo.wait_fleet("the rover placed", |s| {
        s["vehicles"][0]["position"].is_array()
    })
    .await;

    // Paused from the FPMo: what follows happens while it waits.
    let (status, answer) = fpmo
        .post(
            "/api/fleet/command",
            serde_json::json!({"vehicle": "helper", "action": "pause"}),
        )
        .await;
    assert_eq!((status, &answer["answer"]), (200, &"helper paused".into()));
    // #1 nearest (taken at once, as the only point), then #2, #3, #4 farther.
    for p in [at(15.0, 0.0), at(0.0, 40.0), at(60.0, 0.0), at(0.0, -50.0)] {
        let (status, answer) = add(&fpmo, p).await;
        assert_eq!(status, 200, "{answer}");
    }
    let (status, answer) = add(&fpmo, at(-90.0, 0.0)).await;
    assert_eq!(status, 502, "{answer}");
    let why = answer["error"].as_str().unwrap_or_default();
    assert!(why.contains("inside obstacle `shed`"), "{why}");
    fpmo.wait_fleet("the four points", |s| operator_points(s).len() == 4)
        .await;

    match Browser::start().await {
        Some(browser) => {
            browser
                .goto(&format!("http://{}/fleet?token={}", fpmo.addr, fpmo.token))
                .await;
            let row = |id: u32| format!("#points [data-point='operator:{id}']");
            browser
                .wait_for(
                    "the points waiting",
                    &format!("return !!document.querySelector(\"{}\");", row(4)),
                )
                .await;
            // #4 first, then #3 first, then #3 down below #4: the order is #4, #3.
            browser.click(&format!("{} [data-act=first]", row(4))).await;
            browser
                .wait_for(
                    "#4 in the order",
                    &format!(
                        "return !!document.querySelector(\"{} [data-act=up]\");",
                        row(4)
                    ),
                )
                .await;
            browser.click(&format!("{} [data-act=first]", row(3))).await;
            browser
                .wait_for(
                    "#3 in the order",
                    &format!(
                        "return !!document.querySelector(\"{} [data-act=up]\");",
                        row(3)
                    ),
                )
                .await;
            browser.click(&format!("{} [data-act=down]", row(3))).await;
            fpmo.wait_fleet("#4 then #3", |s| {
                s["visit_first"] == serde_json::json!([["operator", 4], ["operator", 3]])
            })
            .await;
            browser
                .wait_for(
                    "#2 listed",
                    &format!("return !!document.querySelector(\"{}\");", row(2)),
                )
                .await;
            browser
                .click(&format!("{} [data-act=delete]", row(2)))
                .await;
            // A point added with a click on the map, a quarter of the way in from its
            // top-left corner, then deleted again.
            browser.click("#addpoint").await;
            browser
                .eval(
                    "const m = document.getElementById('map'); const r = m.getBoundingClientRect(); \
                     m.dispatchEvent(new MouseEvent('click', {clientX: r.left + r.width / 4, \
                     clientY: r.top + r.height / 4, bubbles: true})); return true;",
                )
                .await;
            fpmo.wait_fleet("the point clicked on the map", |s| {
                operator_points(s).len() == 5
            })
            .await;
            browser
                .wait_for(
                    "#5 listed",
                    &format!("return !!document.querySelector(\"{}\");", row(5)),
                )
                .await;
            browser
                .click(&format!("{} [data-act=delete]", row(5)))
                .await;
            browser.close().await;
        }
        None => {
            test_support::tool_missing("chromium/chromedriver", "run .ci/install-chromium");
            // The same edits through the API the page uses.
            let order = serde_json::json!({"edit": {"Order": {"points": [["operator", 4], ["operator", 3]]}}});
            assert_eq!(fpmo.post("/api/fleet/points", order).await.0, 200);
            let del = serde_json::json!({"edit": {"Delete": {"by": "operator", "id": 2}}});
            assert_eq!(fpmo.post("/api/fleet/points", del).await.0, 200);
        }
    }
    let s = fpmo
        .wait_fleet("#2 deleted", |s| {
            operator_points(s).contains(&(2, false, true))
        })
        .await;
    let s = &s["fleets"][0]["status"];
    assert!(
        s["visit_order"].as_array().is_some_and(Vec::is_empty),
        "nothing visited while paused: {s}"
    );

    // Resumed from the FPMo: #1 (taken before the edits), then the operator's order.
    let (status, answer) = fpmo
        .post(
            "/api/fleet/command",
            serde_json::json!({"vehicle": "helper", "action": "resume"}),
        )
        .await;
    assert_eq!((status, &answer["answer"]), (200, &"helper resumed".into()));
    let s = fpmo
        .wait_fleet("#1, #4 and #3 visited", |s| {
            s["visit_order"].as_array().is_some_and(|v| v.len() >= 3)
        })
        .await;
    let s = &s["fleets"][0]["status"];
    assert_eq!(s["visit_order"], serde_json::json!([1, 4, 3]), "{s}");
    let points = operator_points(s);
    assert!(
        points.contains(&(2, false, true)) && !points.iter().any(|p| p.0 == 5 && !p.2),
        "the deleted points were not visited: {points:?}"
    );
    assert_eq!(s["vehicles"][0]["paused"], false);
    fpmo.kill().await;
}
