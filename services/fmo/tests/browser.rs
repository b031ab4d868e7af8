//! The FMo page in headless Chromium (WebDriver through chromedriver) against real `mavsim` and
//! `vas` processes: the allowed transitions are the only buttons, a click changes the state,
//! Space + W on the keyboard drives the rover forward, releasing stops it; the autopilot's
//! parameters are read, filtered and one is set from the page; a screenshot is saved
//! to `<target>/tmp/fmo-page.png`. Skips (passing) when chromium or chromedriver is missing:
//! `.ci/install-chromium` installs them.

mod common;

use std::time::Duration;

use common::*;

const SPACE: &str = "\u{E00D}";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn pilot_drives_from_the_page() {
    build_flight_bins();
    tokio::time::timeout(Duration::from_secs(240), scenario())
        .await
        .expect("scenario timed out");
}

fn speed_and_pos(s: &serde_json::Value) -> (f64, f64, f64, f64) {
    let p = &vehicle(s, "rover1").expect("rover1")["position"]["value"];
    let f = |k: &str| p[k].as_f64().unwrap_or(f64::NAN);
    (f("lat"), f("lon"), f("heading"), f("speed"))
}

async fn scenario() {
    let Some(browser) = Browser::start().await else {
        test_support::tool_missing("chromium/chromedriver", "run .ci/install-chromium");
        return;
    };
    let domain = unique_domain("fmo-browser");
    let (sim, vas) = rover(&domain, 2.0).await;
    let fmo = Station::start(env!("CARGO_BIN_EXE_fmo"), "FMO_URL", &["--domain", &domain]).await;
    browser.goto(&fmo.url).await;

    // PARKING, with MANUAL_NAVIGATION offered and nothing a rover cannot do.
    browser
        .wait_for(
            "PARKING with its buttons",
            "return document.getElementById('fs')?.textContent === 'PARKING' && \
             !!document.querySelector('button.transition[data-to=MANUAL_NAVIGATION]:not([disabled])');",
        )
        .await;
    // The instruments: the battery's charge and voltage, and the Services panel and the
    // vehicle commands (ARM, DIRECTED's form) drawn.
    browser
        .wait_for(
            "the battery row",
            "const c = document.querySelector('#t-battery td:last-child'); \
             return !!c && c.textContent.includes('%') && c.textContent.includes(' V');",
        )
        .await;
    browser
        .wait_for(
            "the Services panel and the commands",
            "return !!document.getElementById('services') && \
             !!document.querySelector('button.vcmd[data-cmd=ARM]') && \
             !!document.getElementById('d-fly') && !!document.getElementById('t-plan');",
        )
        .await;
    // The autopilot's parameters: read through the VAS, filtered, one set as a command the
    // VAS confirms with the value the autopilot took.
    browser.click("#readparams").await;
    browser
        .wait_for(
            "the parameters read",
            "return !!document.querySelector('#params tr[data-param=CRUISE_SPEED]') && \
               document.getElementById('paramnote').textContent.includes('parameters of rover1');",
        )
        .await;
    browser.send_keys("#pfilter", "CRUISE").await;
    browser
        .wait_for(
            "the filter applied",
            "const rows = document.querySelectorAll('#params tr'); \
             return rows.length > 0 && Array.from(rows).every((r) => r.dataset.param.includes('CRUISE'));",
        )
        .await;
    browser
        .send_keys("#params tr[data-param=CRUISE_SPEED] input.pin", "2.5")
        .await;
    browser
        .click("#params tr[data-param=CRUISE_SPEED] button.setparam")
        .await;
    browser
        .wait_for(
            "the parameter set",
            "return Array.from(document.querySelectorAll('#commands li[data-status=ok]')) \
               .some((l) => l.textContent.includes('set_param CRUISE_SPEED = 2.5') && l.textContent.includes('CRUISE_SPEED is 2.5'));",
        )
        .await;
    let offered = browser
        .eval("return Array.from(document.querySelectorAll('button.transition')).map(b => b.dataset.to);")
        .await;
    let offered: Vec<&str> = offered
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|v| v.as_str())
        .collect();
    for never in ["PARKING", "TAKE_OFF", "LANDING"] {
        assert!(!offered.contains(&never), "{never} offered: {offered:?}");
    }

    browser
        .click("button.transition[data-to=MANUAL_NAVIGATION]")
        .await;
    browser
        .wait_for(
            "MANUAL_NAVIGATION confirmed",
            "return document.getElementById('fs')?.textContent === 'MANUAL_NAVIGATION' && \
             !!document.querySelector('#commands li[data-status=ok]');",
        )
        .await;

    // Space (dead-man) + W: the page shows the dead-man held and the rover moves forward.
    let before = speed_and_pos(&fmo.get_json("/api/state").await);
    browser.keys(&[SPACE, "w"], true).await;
    browser
        .wait_for(
            "the dead-man held",
            "return document.getElementById('deadman').className === 'held';",
        )
        .await;
    tokio::time::sleep(Duration::from_secs(3)).await;
    let shot = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("fmo-page.png");
    browser.screenshot(&shot).await;
    eprintln!("screenshot: {}", shot.display());
    let during = speed_and_pos(&fmo.get_json("/api/state").await);
    browser.keys(&[SPACE, "w"], false).await;
    let r = 6_371_000.0_f64;
    let n = (during.0 - before.0).to_radians() * r;
    let e = (during.1 - before.1).to_radians() * r * before.0.to_radians().cos();
    let along = n * before.2.to_radians().cos() + e * before.2.to_radians().sin();
    assert!(
        along > 0.5,
        "moved {along:.2} m along the heading ({n:.2} N, {e:.2} E)"
    );
    browser
        .wait_for(
            "the dead-man released",
            "return document.getElementById('deadman').className === 'released';",
        )
        .await;
    fmo.wait_state("the rover stopped", |s| speed_and_pos(s).3 < 0.1)
        .await;

    browser.close().await;
    fmo.kill().await;
    vas.kill().await;
    sim.kill().await;
}
