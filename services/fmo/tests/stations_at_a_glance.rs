//! Both stations read at a glance, in headless Chromium against real `mavsim`, `vas`, `fpma
//! run`, `fmo` and `fpmo` processes flying the failsafe field plan (a fence around the field):
//! the FMo's instrument strip (attitude, heading, altitude, speed, battery with time left, plan
//! ETA, link quality) and map (the vehicle, its home, the fence, the plan's numbered waypoints,
//! a legend), the FPMo's battery, ETA and the same map; with a tile server that cannot be
//! reached, both draw the grid and say why; the FPMo's plan events read in words; and a
//! flight log played back (`replay/status` published) puts both under a REPLAY banner; the
//! FPMa answers its last progress on request.
//! Screenshots go to `<target>/tmp/`.

mod common;

use std::time::Duration;

use common::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn both_stations_show_instruments_fence_home_waypoints_and_eta() {
    build_flight_bins();
    let fpmo_bin = workspace_bin("fpmo");
    tokio::time::timeout(Duration::from_secs(240), scenario(&fpmo_bin))
        .await
        .expect("scenario timed out");
}

/// A tile template on a local port nothing listens on: every tile fails at once.
fn unreachable_tiles() -> String {
    let port = test_support::free_tcp_port();
    format!("http://127.0.0.1:{port}/{{z}}/{{x}}/{{y}}.png")
}

/// Publishes `replay/status` as `usal replay` does, twice a second, until dropped.
async fn replaying(domain: &str) -> (marea::Node, tokio::task::JoinHandle<()>) {
    let mut net = marea::NetworkConfig::ethernet_loopback("replayer");
    net.domain = domain.to_owned();
    let node = marea::Node::open(&net).await.expect("replayer node");
    let svc = node.service("replay").expect("replay service");
    let status = svc
        .publish_variable::<usal_types::ReplayStatus>("status")
        .expect("replay/status");
    let task = tokio::spawn(async move {
        for tick in 0u32.. {
            let _ = status.set(&usal_types::ReplayStatus {
                log: "flight.jsonl.gz".into(),
                mission: "rover-demo".into(),
                flown_utc: "2026-11-28T14:00:00Z".into(),
                at_s: f64::from(tick) / 2.0,
                duration_s: 300.0,
                speed: 1.0,
                ended: false,
            });
            tokio::time::sleep(Duration::from_millis(500)).await;
        }
    });
    (node, task)
}

/// The REPLAY banner, naming the recorded mission.
const REPLAY_BANNER: &str = "const r = document.getElementById('replay');      return r.style.display === 'block' && r.textContent.startsWith('REPLAY of mission rover-demo');";

/// What `canvas#map` says it drew, and whether the legend lists each layer.
const MAP_DRAWN: &str = "const m = document.getElementById('map'); \
     const k = (x) => !!document.querySelector(`#legend li[data-key=${x}]`); \
     return !!m && m.dataset.vehicles === '1' && m.dataset.home === '1' && \
       m.dataset.fence.includes('circle') && m.dataset.fence.includes('polygon') && \
       Number(m.dataset.waypoints) >= 3 && \
       k('vehicle') && k('home') && k('fence') && k('waypoints') && k('plan');";

/// The grid under the map and the status saying the tiles cannot be reached.
const GRID_FALLBACK: &str = "const m = document.getElementById('map'); \
     const s = document.getElementById('mapstatus').textContent; \
     return !!m.dataset.grid && m.dataset.tiles === 'unreachable' && s.includes('unreachable') && \
       s.includes('--tiles FILE.mbtiles');";

async fn scenario(fpmo_bin: &std::path::Path) {
    let Some(browser) = Browser::start().await else {
        test_support::tool_missing("chromium/chromedriver", "run .ci/install-chromium");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let domain = unique_domain("glance");
    let (sim, vas) = rover(&domain, 2.0).await;
    let fpma = fpma_rover1(&domain, dir.path()).await;
    let tiles = unreachable_tiles();
    let station_args = ["--domain", domain.as_str(), "--tiles", tiles.as_str()];
    let fpmo = Station::start(&fpmo_bin.display().to_string(), "FPMO_URL", &station_args).await;
    let fmo = Station::start(env!("CARGO_BIN_EXE_fmo"), "FMO_URL", &station_args).await;

    // The failsafe field plan (its fence: 250 m around home and the field's polygon), started.
    let xml = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../config/flightplans/rover-failsafe.xml"
    ))
    .unwrap();
    fpmo.wait_state("the FPMa reachable", |s| {
        vehicle(s, "rover1").is_some_and(|v| v["fpma_reachable"] == true)
    })
    .await;
    let (status, body) = fpmo
        .post(
            "/api/upload",
            serde_json::json!({"file": "rover-failsafe.xml", "xml": xml}),
        )
        .await;
    assert_eq!(status, 202, "{body}");
    let id = body["id"].as_u64().unwrap();
    fpmo.wait_state("the plan loaded", |s| {
        command(s, id).is_some_and(|c| c["status"] == "ok")
    })
    .await;
    fpmo.wait_state("Start offered", |s| {
        vehicle(s, "rover1").is_some_and(|v| {
            v["offers"]
                .as_array()
                .is_some_and(|o| o.iter().any(|o| o["label"] == "Start"))
        })
    })
    .await;
    let (status, body) = fpmo
        .post(
            "/api/change_state",
            serde_json::json!({"to": "WAYPOINT_NAVIGATION"}),
        )
        .await;
    assert_eq!(status, 202, "{body}");

    // The FMo: instruments for the commanded vehicle.
    browser.goto(&fmo.url).await;
    browser
        .wait_for(
            "the instruments: attitude, heading, altitude, speed",
            "const a = document.getElementById('i-attitude'), h = document.getElementById('i-heading'); \
             return a.dataset.roll !== undefined && a.dataset.roll !== '' && \
               h.dataset.heading !== undefined && h.dataset.heading !== '' && \
               document.getElementById('i-alt').textContent.endsWith(' m') && \
               document.getElementById('i-speed').textContent.endsWith(' m/s');",
        )
        .await;
    browser
        .wait_for(
            "the battery with its time left",
            "const b = document.getElementById('i-battery').textContent; \
             const l = document.getElementById('i-batleft').textContent; \
             return b.includes('%') && b.includes(' V') && (l.includes('left') || l.includes('measuring'));",
        )
        .await;
    browser
        .wait_for(
            "the plan's ETA",
            "return /^ETA \\d+:\\d\\d$/.test(document.getElementById('i-eta').textContent);",
        )
        .await;
    browser
        .wait_for(
            "the link's quality",
            "const l = document.getElementById('i-link'); \
             return ['good', 'fair', 'poor'].includes(l.dataset.grade) && \
               document.getElementById('i-linkdetail').textContent.includes('heard');",
        )
        .await;
    // The map: the vehicle, its home, the fence, the numbered waypoints and the legend; the
    // grid where the tiles cannot be loaded.
    browser.wait_for("the FMo's map", MAP_DRAWN).await;
    browser
        .wait_for("the FMo's grid and why", GRID_FALLBACK)
        .await;
    let shot = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("fmo-glance.png");
    browser.screenshot(&shot).await;
    eprintln!("screenshot: {}", shot.display());
    // No banner on a live flight; a flight log played back into the domain raises it.
    let banner = browser
        .eval("return document.getElementById('replay').style.display;")
        .await;
    assert_eq!(banner, "none");
    let (replayer, replay_task) = replaying(&domain).await;
    // The FPMa's last progress on request (what `usal run` asks when a lossy radio lost the
    // variable's last value): the plan flying.
    let progress = replayer
        .service("asker")
        .unwrap()
        .function::<(), flightplan::api::Progress>("rover1/fpma/progress")
        .unwrap();
    assert!(
        progress.wait_provider(Duration::from_secs(10)).await,
        "no fpma/progress"
    );
    let p = progress
        .call(&(), Duration::from_secs(5))
        .await
        .expect("the FPMa's progress");
    assert_eq!((p.plan.as_str(), p.version), ("failsafe-field", 1), "{p:?}");
    assert!(p.fraction > 0.0 && !p.completed, "{p:?}");
    browser
        .wait_for("the FMo's REPLAY banner", REPLAY_BANNER)
        .await;

    // The FPMo: battery, ETA and the same map.
    browser.goto(&fpmo.url).await;
    browser
        .wait_for(
            "the FPMo's battery and ETA",
            "const b = document.getElementById('battery')?.textContent || ''; \
             const e = document.getElementById('eta')?.textContent || ''; \
             return b.includes('%') && b.includes(' V') && /ETA \\d+:\\d\\d/.test(e);",
        )
        .await;
    browser.wait_for("the FPMo's map", MAP_DRAWN).await;
    browser
        .wait_for(
            "the plan's events in words",
            "const e = Array.from(document.querySelectorAll('#events li')).map((l) => l.textContent); \
             return e.some((t) => /^v\\d+: leg `[^`]+` started/.test(t)) && !e.some((t) => t.includes('{'));",
        )
        .await;
    browser
        .wait_for("the FPMo's REPLAY banner", REPLAY_BANNER)
        .await;
    browser
        .wait_for("the FPMo's grid and why", GRID_FALLBACK)
        .await;
    let shot = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("fpmo-glance.png");
    browser.screenshot(&shot).await;
    eprintln!("screenshot: {}", shot.display());

    browser.close().await;
    replay_task.abort();
    drop(replayer);
    fmo.kill().await;
    fpmo.kill().await;
    fpma.kill().await;
    vas.kill().await;
    sim.kill().await;
}
