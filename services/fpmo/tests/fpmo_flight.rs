//! The `fpmo` binary over HTTP against real processes: `mavsim`, `vas` and `fpma run` (built
//! with `cargo build` into this test's target directory). Upload the car-park plan through the
//! station, see its legs and the progress advance; a second station started after the upload
//! draws the plan it did not upload (the FPMa's `plan` variable); skip a leg, widen the scan and
//! see both stations redraw it; set a plan variable, go to the approach stage; kill the FPMa (stale, command failed, station still answering)
//! and bring it back (recovered, no reload).

#[path = "../../fmo/tests/common/mod.rs"]
mod common;

use std::time::Duration;

use common::*;

fn progress(s: &serde_json::Value) -> &serde_json::Value {
    &vehicle(s, "rover1").expect("rover1")["progress"]["value"]
}

async fn wait_command(st: &Station, id: u64, want: &str) -> serde_json::Value {
    let s = st
        .wait_state(&format!("command {id} finished"), |s| {
            command(s, id).is_some_and(|c| c["status"] != "pending")
        })
        .await;
    let c = command(&s, id).unwrap().clone();
    assert_eq!(c["status"], want, "{c:#}");
    c
}

/// Polls `GET /api/plan` until the plan satisfies `pred`.
async fn wait_plan(
    st: &Station,
    what: &str,
    mut pred: impl FnMut(&serde_json::Value) -> bool,
) -> serde_json::Value {
    let deadline = tokio::time::Instant::now() + STEP;
    loop {
        let (status, body) = st.get("/api/plan?vehicle=rover1").await;
        if status == 200 {
            let p: serde_json::Value = serde_json::from_str(&body).expect("plan JSON");
            if pred(&p) {
                return p;
            }
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "never saw {what}; last answer {status} {body}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fly_the_carpark_from_the_station() {
    build_flight_bins();
    tokio::time::timeout(Duration::from_secs(300), scenario())
        .await
        .expect("scenario timed out");
}

async fn scenario() {
    let dir = tempfile::tempdir().unwrap();
    let domain = unique_domain("fpmo");
    let fpma_bin = workspace_bin("fpma");
    let (sim, vas) = rover(&domain, 10.0).await;
    let fpma = Proc::start(&fpma_bin, &fpma_rover1_args(&domain, dir.path()), false).await;
    let st = Station::start(
        env!("CARGO_BIN_EXE_fpmo"),
        "FPMO_URL",
        &["--domain", &domain, "--call-timeout-ms", "2000"],
    )
    .await;
    let (status, page) = st.get("/").await;
    assert_eq!(status, 200);
    assert!(page.contains("FPMo — Flight Plan Monitor"));
    assert!(!page.contains("http://") && !page.contains("https://"));

    st.wait_state("rover1 and its FPMa", |s| {
        vehicle(s, "rover1").is_some_and(|v| v["fpma_reachable"] == true)
    })
    .await;

    // A broken plan is refused by the station itself, with its line.
    let (status, body) = st
        .post(
            "/api/upload",
            serde_json::json!({"file": "bad.xml", "xml": "<flightPlan name='x'>\n<bogus/></flightPlan>"}),
        )
        .await;
    assert_eq!(status, 400);
    assert!(
        body["error"].as_str().unwrap().starts_with("bad.xml:2:"),
        "{body}"
    );

    // Upload the car-park plan as the page does: pending, then loaded by the FPMa.
    let xml = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../config/flightplans/rover-carpark.xml"
    ))
    .unwrap();
    let (status, body) = st
        .post(
            "/api/upload",
            serde_json::json!({"file": "rover-carpark.xml", "xml": xml}),
        )
        .await;
    assert_eq!(status, 202, "{body}");
    let c = wait_command(&st, body["id"].as_u64().unwrap(), "ok").await;
    assert!(
        c["detail"]
            .as_str()
            .unwrap()
            .starts_with("loaded as version"),
        "{c}"
    );
    let plan = wait_plan(&st, "the uploaded plan drawn", |p| {
        p["version"].as_u64() >= Some(1)
    })
    .await;
    let legs: Vec<&str> = plan["legs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["id"].as_str().unwrap())
        .collect();
    assert!(legs.contains(&"hold") && legs.contains(&"area"), "{legs:?}");
    assert_eq!(plan["file"], "rover-carpark.xml");

    // A second station, started after the upload, draws the same plan: it never saw the file.
    let late = Station::start(
        env!("CARGO_BIN_EXE_fpmo"),
        "FPMO_URL",
        &["--domain", &domain, "--node", "fpmo-late"],
    )
    .await;
    let late_plan = wait_plan(
        &late,
        "the plan drawn by a station that did not upload it",
        |p| p["version"] == plan["version"],
    )
    .await;
    assert_eq!(late_plan["legs"], plan["legs"]);
    assert_eq!(late_plan["waypoints"], plan["waypoints"]);

    // The same geometry on request: what a station asks for when the `plan` value was lost.
    let mut cfg = marea::NetworkConfig::ethernet_loopback("probe");
    cfg.domain.clone_from(&domain);
    let probe = marea::Node::open(&cfg).await.expect("probe node");
    let svc = probe.service("probe").unwrap();
    let f = svc
        .function::<(), flightplan::api::PlanGeometry>("rover1/fpma/plan_geometry")
        .unwrap();
    assert!(f.wait_provider(STEP).await, "no plan_geometry provider");
    let g = f.call(&(), STEP).await.expect("plan_geometry");
    assert_eq!(Some(g.version), plan["version"].as_u64());
    assert_eq!(g.name, "castelldefels-carpark");
    assert_eq!(g.points.len(), plan["waypoints"].as_array().unwrap().len());
    drop((f, svc));
    probe.shutdown().await;

    // The plan waits for the operator: the station shows the flight state, "plan ready,
    // press Start", and offers exactly what the VAS allows from PARKING, WAYPOINT_NAVIGATION
    // as Start.
    let s = st
        .wait_state("plan ready, press Start", |s| {
            let v = vehicle(s, "rover1").unwrap();
            v["ready"]["ready"] == true
                && v["offers"]
                    .as_array()
                    .is_some_and(|o| o.iter().any(|o| o["label"] == "Start"))
        })
        .await;
    let v = vehicle(&s, "rover1").unwrap();
    assert_eq!(
        v["flight_state"]["value"], "PARKING",
        "the FPMa moved the vehicle by itself"
    );
    assert!(
        v["ready"]["text"].as_str().unwrap().contains("press Start"),
        "{v:#}"
    );
    let offered: Vec<&str> = v["offers"]
        .as_array()
        .unwrap()
        .iter()
        .map(|o| o["to"].as_str().unwrap())
        .collect();
    assert_eq!(
        offered,
        [
            "DIRECTED",
            "MANUAL_NAVIGATION",
            "WAYPOINT_NAVIGATION",
            "RETURN_TO_LAUNCH",
            "MANUAL"
        ]
    );
    // Parked and disarmed: ARM is offered, DISARM is not.
    assert_eq!(v["command_offers"], serde_json::json!(["ARM"]), "{v:#}");
    let (status, body) = st
        .post(
            "/api/vehicle_command",
            serde_json::json!({"command": "DISARM"}),
        )
        .await;
    assert_eq!(status, 409, "{body}");
    let (status, body) = st
        .post(
            "/api/vehicle_command",
            serde_json::json!({"command": "ARM"}),
        )
        .await;
    assert_eq!(status, 202, "{body}");
    wait_command(&st, body["id"].as_u64().unwrap(), "ok").await;
    st.wait_state("armed, DISARM offered", |s| {
        let v = vehicle(s, "rover1").unwrap();
        v["armed"] == true && v["command_offers"] == serde_json::json!(["DISARM"])
    })
    .await;
    // What is not offered is refused by the station itself, naming what is.
    let (status, body) = st
        .post("/api/change_state", serde_json::json!({"to": "LANDING"}))
        .await;
    assert_eq!(status, 409, "{body}");
    assert!(
        body["error"]
            .as_str()
            .unwrap()
            .contains("not offered from PARKING"),
        "{body}"
    );
    let (status, body) = st
        .post(
            "/api/change_state",
            serde_json::json!({"to": "WAYPOINT_NAVIGATION"}),
        )
        .await;
    assert_eq!(status, 202, "{body}");
    let c = wait_command(&st, body["id"].as_u64().unwrap(), "ok").await;
    assert!(c["what"].as_str().unwrap().starts_with("Start"), "{c:#}");
    st.wait_state("WAYPOINT_NAVIGATION shown, no longer ready", |s| {
        let v = vehicle(s, "rover1").unwrap();
        v["flight_state"]["value"] == "WAYPOINT_NAVIGATION" && v["ready"]["ready"] == false
    })
    .await;

    // The progress advances as mavsim drives.
    let s = st
        .wait_state("progress", |s| {
            progress(s)["fraction"].as_f64().unwrap_or(0.0) > 0.0 && progress(s)["leg"].is_string()
        })
        .await;
    assert_eq!(progress(&s)["plan"], "castelldefels-carpark");

    // Skip legs until the hold is current, then skip it: the current leg changes.
    let s = st
        .wait_state("the hold", |s| progress(s)["leg"] == "hold")
        .await;
    let v = progress(&s)["version"].as_u64().unwrap();
    let (_, body) = st
        .post("/api/command", serde_json::json!({"cmd": "skip_leg"}))
        .await;
    wait_command(&st, body["id"].as_u64().unwrap(), "ok").await;
    let s = st
        .wait_state("the leg after the hold", |s| {
            progress(s)["leg"] != "hold" && progress(s)["version"].as_u64() >= Some(v)
        })
        .await;
    // The plan's events read as words, not as the program's data.
    let events: Vec<String> = vehicle(&s, "rover1").expect("rover1")["events"]
        .as_array()
        .expect("events")
        .iter()
        .filter_map(|e| e["text"].as_str().map(str::to_owned))
        .collect();
    assert!(
        events.iter().any(|e| e.ends_with("leg `hold` started")),
        "{events:?}"
    );
    assert!(
        events
            .iter()
            .all(|e| !e.contains('{') && !e.contains("LegStarted")),
        "{events:?}"
    );

    // Widen the scan: confirmed, and the station's copy is redrawn with fewer waypoints.
    let count = |p: &serde_json::Value| {
        p["waypoints"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|w| w["leg"] == "area")
            .count()
    };
    let before = count(&plan);
    let (_, body) = st
        .post(
            "/api/modify_leg",
            serde_json::json!({"leg": "area", "changes": [["spacing", "12"]]}),
        )
        .await;
    wait_command(&st, body["id"].as_u64().unwrap(), "ok").await;
    for station in [&st, &late] {
        let replanned = wait_plan(station, "the scan redrawn", |p| {
            p["version"].as_u64() > plan["version"].as_u64()
        })
        .await;
        assert!(
            count(&replanned) < before,
            "{} !< {before}",
            count(&replanned)
        );
        assert!(replanned["legs"]
            .as_array()
            .unwrap()
            .iter()
            .any(|l| l["id"] == "area" && l["params"]["spacing"] == 12.0));
    }
    late.kill().await;

    // The executive's other commands: a plan variable set and shown with its new value; an
    // unknown one fails with the FPMa's reason; a malformed one is refused by the station; a
    // jump to the approach stage.
    let rover1_var = |s: &serde_json::Value, name: &str| {
        vehicle(s, "rover1").and_then(|v| {
            v["vars"]
                .as_array()?
                .iter()
                .find(|x| x["name"] == name)
                .map(|x| x["value"].clone())
        })
    };
    st.wait_state("the plan variables", |s| {
        rover1_var(s, "inspect") == Some(serde_json::json!(false))
    })
    .await;
    let (status, body) = st
        .post(
            "/api/command",
            serde_json::json!({"cmd": "set_var", "name": "inspect", "value": true}),
        )
        .await;
    assert_eq!(status, 202, "{body}");
    wait_command(&st, body["id"].as_u64().unwrap(), "ok").await;
    st.wait_state("inspect set", |s| {
        rover1_var(s, "inspect") == Some(serde_json::json!(true))
    })
    .await;
    let (_, body) = st
        .post(
            "/api/command",
            serde_json::json!({"cmd": "set_var", "name": "nope", "value": 1}),
        )
        .await;
    let c = wait_command(&st, body["id"].as_u64().unwrap(), "failed").await;
    assert!(c["detail"].as_str().unwrap().contains("nope"), "{c:#}");
    let (status, _) = st
        .post(
            "/api/command",
            serde_json::json!({"cmd": "set_var", "name": "inspect", "value": "yes"}),
        )
        .await;
    assert_eq!(status, 400);
    let (_, body) = st
        .post(
            "/api/command",
            serde_json::json!({"cmd": "goto_stage", "stage": "approach"}),
        )
        .await;
    wait_command(&st, body["id"].as_u64().unwrap(), "ok").await;
    st.wait_state("the approach stage", |s| progress(s)["stage"] == "approach")
        .await;

    // The FPMa dies: stale, a command fails with a reason, the station keeps answering.
    fpma.kill().await;
    st.wait_state("the FPMa unreachable", |s| {
        vehicle(s, "rover1")
            .is_some_and(|v| v["fpma_reachable"] == false && v["progress"]["stale"] == true)
    })
    .await;
    let (_, body) = st
        .post("/api/command", serde_json::json!({"cmd": "pause"}))
        .await;
    let c = wait_command(&st, body["id"].as_u64().unwrap(), "failed").await;
    assert!(!c["detail"].as_str().unwrap().is_empty());
    let mut sse = Sse::open(&st.addr, &st.with_token("/api/events")).await;
    let _ = sse.next("state").await;

    // It comes back: the same stream shows it reachable again.
    let fpma = Proc::start(&fpma_bin, &fpma_rover1_args(&domain, dir.path()), false).await;
    let deadline = tokio::time::Instant::now() + STEP;
    loop {
        let s = sse.next("state").await;
        if vehicle(&s, "rover1").is_some_and(|v| v["fpma_reachable"] == true) {
            break;
        }
        assert!(tokio::time::Instant::now() < deadline, "FPMa never back");
    }

    drop(sse);
    st.kill().await;
    fpma.kill().await;
    vas.kill().await;
    sim.kill().await;
}
