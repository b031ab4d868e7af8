//! The map's optional georeferenced background: `fpmo --background FILE --background-bounds
//! N,W,S,E` tells the page where the image goes and serves the file; bad bounds or a missing
//! file stop the station at start with the reason; in headless Chromium (when installed) the
//! page draws the image under the map.

#[path = "../../fmo/tests/common/mod.rs"]
mod common;

use std::time::Duration;

use common::*;

const SVG: &str = r##"<svg xmlns="http://www.w3.org/2000/svg" width="64" height="64"><rect width="64" height="64" fill="#264"/></svg>"##;

/// Runs `fpmo args`, expecting it to fail at start: its stderr.
async fn fails(args: &[&str]) -> String {
    station_fails_at_start(env!("CARGO_BIN_EXE_fpmo"), args).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn background_image_under_the_map() {
    tokio::time::timeout(Duration::from_secs(120), scenario())
        .await
        .expect("scenario timed out");
}

async fn scenario() {
    let dir = tempfile::tempdir().unwrap();
    let image = dir.path().join("field.svg");
    std::fs::write(&image, SVG).unwrap();
    let image = image.display().to_string();

    let err = fails(&[
        "--background",
        &image,
        "--background-bounds",
        "41.3,1.98,41.2",
    ])
    .await;
    assert!(err.contains("NORTH,WEST,SOUTH,EAST"), "{err}");
    let err = fails(&[
        "--background",
        &image,
        "--background-bounds",
        "41.2,1.98,41.3,1.99",
    ])
    .await;
    assert!(err.contains("north must exceed south"), "{err}");
    let missing = dir.path().join("none.png").display().to_string();
    let err = fails(&[
        "--background",
        &missing,
        "--background-bounds",
        "41.3,1.98,41.2,1.99",
    ])
    .await;
    assert!(err.contains("background image"), "{err}");

    let domain = unique_domain("fpmo-bg");
    let st = Station::start(
        env!("CARGO_BIN_EXE_fpmo"),
        "FPMO_URL",
        &[
            "--domain",
            &domain,
            "--background",
            &image,
            "--background-bounds",
            "41.2765,1.9865,41.2745,1.9885",
        ],
    )
    .await;
    let c = st.get_json("/api/config").await;
    assert_eq!(
        c["background"],
        serde_json::json!({"url": "/api/background", "north": 41.2765, "west": 1.9865,
                           "south": 41.2745, "east": 1.9885})
    );
    assert_eq!(st.get("/api/background").await, (200, SVG.to_owned()));

    if let Some(browser) = Browser::start().await {
        browser.goto(&st.url).await;
        browser
            .wait_for(
                "the background drawn",
                "return document.getElementById('map').dataset.background === 'drawn';",
            )
            .await;
        browser
            .eval("const b = document.getElementById('bgshow'); b.click(); return true;")
            .await;
        browser
            .wait_for(
                "the background hidden",
                "return document.getElementById('map').dataset.background === '';",
            )
            .await;
        browser.close().await;
    } else {
        test_support::tool_missing(
            "chromium/chromedriver (the browser part)",
            "run .ci/install-chromium",
        );
    }

    // Without a background the page is told so and nothing is served.
    let plain = Station::start(
        env!("CARGO_BIN_EXE_fpmo"),
        "FPMO_URL",
        &["--domain", &domain],
    )
    .await;
    assert_eq!(
        plain.get_json("/api/config").await["background"],
        serde_json::Value::Null
    );
    assert_eq!(plain.get("/api/background").await.0, 404);
    plain.kill().await;
    st.kill().await;
}
