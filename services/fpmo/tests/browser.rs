//! The FPMo page in headless Chromium against `mavsim`, `vas` and `fpma run`: the car-park plan
//! chosen in the page's file input is uploaded and loaded, its legs listed with the current one
//! highlighted, the vehicle waits in PARKING with "press Start" until its Start button is
//! clicked, the progress advances, "skip leg" changes the current leg, "hold here" and
//! "exit hold now" interrupt and resume the plan, a plan variable is set from its row, and the
//! units change what the page shows; a screenshot is saved to `<target>/tmp/fpmo-page.png`. Skips (passing)
//! without chromium and chromedriver (`.ci/install-chromium`).

#[path = "../../fmo/tests/common/mod.rs"]
mod common;

use std::time::Duration;

use common::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn operator_uploads_and_skips_from_the_page() {
    build_flight_bins();
    tokio::time::timeout(Duration::from_secs(240), scenario())
        .await
        .expect("scenario timed out");
}

async fn scenario() {
    let Some(browser) = Browser::start().await else {
        test_support::tool_missing("chromium/chromedriver", "run .ci/install-chromium");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let domain = unique_domain("fpmo-browser");
    let (sim, vas) = rover(&domain, 5.0).await;
    let fpma_args = fpma_rover1_args(&domain, dir.path());
    let fpma = Proc::start(&workspace_bin("fpma"), &fpma_args, false).await;
    let st = Station::start(
        env!("CARGO_BIN_EXE_fpmo"),
        "FPMO_URL",
        &["--domain", &domain],
    )
    .await;
    browser.goto(&st.url).await;
    browser
        .wait_for(
            "the FPMa reachable",
            "return document.getElementById('fpma')?.textContent === 'reachable';",
        )
        .await;

    // Choose the plan file in the page: it is uploaded and loaded.
    let plan = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../config/flightplans/rover-carpark.xml"
    );
    let plan = std::fs::canonicalize(plan).expect("rover-carpark.xml");
    browser
        .send_keys("#file", &plan.display().to_string())
        .await;
    browser
        .wait_for(
            "the upload confirmed",
            "const c = document.querySelector('#commands li'); \
             return c && c.dataset.status === 'ok' && c.textContent.includes('loaded as version');",
        )
        .await;
    browser
        .wait_for(
            "the legs, the current one highlighted",
            "return !!document.querySelector('#legs tr[data-leg=area]') && \
             !!document.querySelector('#legs tr.current');",
        )
        .await;
    // The plan waits for the operator: the vehicle panel shows PARKING, "press Start", and
    // the VAS's allowed changes as buttons, WAYPOINT_NAVIGATION reading Start; click it.
    browser
        .wait_for(
            "PARKING, plan ready, a Start button",
            "const b = document.querySelector('#offers button.offer[data-to=WAYPOINT_NAVIGATION]'); \
             const r = document.getElementById('readytext'); \
             return document.getElementById('flightstate')?.textContent === 'PARKING' && \
               !!b && b.textContent === 'Start' && !!r && r.textContent.includes('press Start') && \
               !document.querySelector('#offers button.offer[data-to=TAKE_OFF]');",
        )
        .await;
    browser
        .click("#offers button.offer[data-to=WAYPOINT_NAVIGATION]")
        .await;
    browser
        .wait_for(
            "WAYPOINT_NAVIGATION shown",
            "return document.getElementById('flightstate')?.textContent === 'WAYPOINT_NAVIGATION';",
        )
        .await;
    browser
        .wait_for(
            "progress",
            "return parseFloat(document.getElementById('pbar').style.width) > 0;",
        )
        .await;

    // Skip the current leg from the page: confirmed, and another leg becomes current.
    let cur = browser
        .eval("return document.querySelector('#legs tr.current').dataset.leg;")
        .await;
    browser.click("#skip").await;
    browser
        .wait_for(
            "skip confirmed",
            "const c = document.querySelector('#commands li'); \
             return c && c.textContent.includes('skip_leg') && c.dataset.status === 'ok';",
        )
        .await;
    browser
        .wait_for(
            "another current leg",
            &format!(
                "const r = document.querySelector('#legs tr.current'); return r && r.dataset.leg !== {cur};"
            ),
        )
        .await;

    // Hold here from the page: confirmed, and the current leg is the commanded hold; exit it
    // at once: confirmed, and the interrupted leg is current again.
    browser.click("#holdhere").await;
    browser
        .wait_for(
            "hold here confirmed",
            "const c = document.querySelector('#commands li'); \
             return c && c.textContent.includes('hold_here') && c.dataset.status === 'ok';",
        )
        .await;
    browser
        .wait_for(
            "the commanded hold current",
            "const l = document.getElementById('curleg'); return l && l.textContent.startsWith('hold-here');",
        )
        .await;
    browser.click("#exitholdnow").await;
    browser
        .wait_for(
            "exit hold confirmed",
            "const c = document.querySelector('#commands li'); \
             return c && c.textContent.includes('exit_hold now') && c.dataset.status === 'ok';",
        )
        .await;
    browser
        .wait_for(
            "the plan's leg current again",
            "const l = document.getElementById('curleg'); return l && !l.textContent.startsWith('hold-here');",
        )
        .await;

    // A plan variable set from its row: confirmed and shown.
    browser
        .click("#vars tr[data-var=inspect] button.setvar")
        .await;
    browser
        .wait_for(
            "inspect shown true",
            "const r = document.querySelector('#vars tr[data-var=inspect] .val'); return r && r.textContent === 'true';",
        )
        .await;

    // Units: feet change the figures shown.
    browser
        .eval("const u = document.getElementById('units'); u.value = 'ft'; u.dispatchEvent(new Event('change')); return true;")
        .await;
    browser
        .wait_for(
            "distances in feet",
            "return document.getElementById('progress')?.textContent.includes(' ft');",
        )
        .await;
    let shot = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("fpmo-page.png");
    browser.screenshot(&shot).await;
    eprintln!("screenshot: {}", shot.display());

    browser.close().await;
    st.kill().await;
    fpma.kill().await;
    vas.kill().await;
    sim.kill().await;
}
