//! Map tiles under the FPMo's map: `fpmo --tiles FILE.mbtiles` serves the tiles of a local
//! MBTiles file itself (a field laptop is often offline), rows flipped from TMS to the page's
//! XYZ; a local `{z}/{x}/{y}` directory template is served the same way; an http(s) template is
//! handed to the browser; vector or broken MBTiles files stop the station at start with the
//! reason; in headless Chromium (when installed) the page draws the tiles. Without `--tiles`
//! the map is OpenStreetMap's, with its credit; `--tiles none` leaves the grid alone.

#[path = "../../fmo/tests/common/mod.rs"]
mod common;

use std::time::Duration;

use common::*;

/// A 1x1 PNG (a green pixel).
const PNG: &str = "89504e470d0a1a0a0000000d4948445200000001000000010802000000907753de0000000c49444154789c63504a730100017a00cd59fb7f4b0000000049454e44ae426082";

fn png() -> Vec<u8> {
    (0..PNG.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&PNG[i..i + 2], 16).unwrap())
        .collect()
}

/// An MBTiles file over the Castelldefels test field: the XYZ tile 3/4/2 (TMS row 5) and
/// 1/1/0 (TMS row 1), in `format`.
fn mbtiles(path: &std::path::Path, format: &str) {
    let db = rusqlite::Connection::open(path).unwrap();
    db.execute_batch(
        "CREATE TABLE metadata (name TEXT, value TEXT);
         CREATE TABLE tiles (zoom_level INTEGER, tile_column INTEGER, tile_row INTEGER, tile_data BLOB);
         CREATE UNIQUE INDEX tile_index ON tiles (zoom_level, tile_column, tile_row);",
    )
    .unwrap();
    for (k, v) in [
        ("name", "field"),
        ("format", format),
        ("bounds", "1.9865,41.2745,1.9885,41.2765"),
        ("attribution", "made by the test"),
    ] {
        db.execute("INSERT INTO metadata VALUES (?1, ?2)", [k, v])
            .unwrap();
    }
    for (z, x, row) in [(3u32, 4u32, 5u32), (1, 1, 1)] {
        db.execute(
            "INSERT INTO tiles VALUES (?1, ?2, ?3, ?4)",
            rusqlite::params![z, x, row, png()],
        )
        .unwrap();
    }
}

/// Runs `fpmo args`, expecting it to fail at start: its stderr.
async fn fails(args: &[&str]) -> String {
    station_fails_at_start(env!("CARGO_BIN_EXE_fpmo"), args).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn map_tiles_from_mbtiles_a_directory_or_a_url() {
    tokio::time::timeout(Duration::from_secs(150), scenario())
        .await
        .expect("scenario timed out");
}

async fn scenario() {
    let dir = tempfile::tempdir().unwrap();
    let vector = dir.path().join("vector.mbtiles");
    mbtiles(&vector, "pbf");
    let err = fails(&["--tiles", &vector.display().to_string()]).await;
    assert!(err.contains("vector tiles"), "{err}");
    let junk = dir.path().join("junk.mbtiles");
    std::fs::write(&junk, "this is not SQLite").unwrap();
    let err = fails(&["--tiles", &junk.display().to_string()]).await;
    assert!(
        err.contains("MBTiles") && err.contains("junk.mbtiles"),
        "{err}"
    );
    let err = fails(&["--tiles", "https://tiles.example/{z}/{x}.png"]).await;
    assert!(err.contains("{z}, {x} and {y}"), "{err}");

    // An MBTiles file, served by the station.
    let file = dir.path().join("field.mbtiles");
    mbtiles(&file, "png");
    let domain = unique_domain("fpmo-tiles");
    let st = Station::start(
        env!("CARGO_BIN_EXE_fpmo"),
        "FPMO_URL",
        &["--domain", &domain, "--tiles", &file.display().to_string()],
    )
    .await;
    let c = st.get_json("/api/map").await;
    assert_eq!(
        c["tiles"],
        serde_json::json!({"url": "/api/tiles/{z}/{x}/{y}", "minzoom": 1, "maxzoom": 3,
            "bounds": [1.9865, 41.2745, 1.9885, 41.2765], "attribution": "made by the test"})
    );
    let tile = String::from_utf8_lossy(&png()).into_owned();
    assert_eq!(st.get("/api/tiles/3/4/2").await, (200, tile.clone()));
    assert_eq!(st.get("/api/tiles/1/1/0.png").await, (200, tile.clone()));
    // The TMS row itself is not the XYZ row; outside the grid and unknown tiles are 404.
    assert_eq!(st.get("/api/tiles/3/4/5").await.0, 404);
    assert_eq!(st.get("/api/tiles/3/9/2").await.0, 404);
    assert_eq!(st.get("/api/tiles/40/0/0").await.0, 404);
    assert_eq!(st.get("/api/tiles/3/4/x").await.0, 400);
    // Without the station's token nothing is served.
    assert_eq!(
        request(&st.addr, "GET", "/api/tiles/3/4/2", None).await.0,
        401
    );

    if let Some(browser) = Browser::start().await {
        browser.goto(&st.url).await;
        let drawn = browser
            .wait_for(
                "the tiles drawn",
                "return document.getElementById('map').dataset.tiles;",
            )
            .await;
        assert_eq!(drawn, "z3:1");
        let credit = browser
            .eval("return document.getElementById('mapstatus').textContent;")
            .await;
        assert_eq!(credit, "map tiles made by the test");
        browser
            .eval("document.getElementById('tilesshow').click(); return true;")
            .await;
        browser
            .wait_for(
                "the tiles hidden",
                "return document.getElementById('map').dataset.tiles === '';",
            )
            .await;
        browser.close().await;
    } else {
        test_support::tool_missing(
            "chromium/chromedriver (the browser part)",
            "run .ci/install-chromium",
        );
    }
    st.kill().await;

    // A directory of tiles, served too; a URL template, left to the browser.
    std::fs::create_dir_all(dir.path().join("tiles/3/4")).unwrap();
    std::fs::write(dir.path().join("tiles/3/4/2.png"), "a tile").unwrap();
    let template = format!("{}/tiles/{{z}}/{{x}}/{{y}}.png", dir.path().display());
    let local = Station::start(
        env!("CARGO_BIN_EXE_fpmo"),
        "FPMO_URL",
        &["--domain", &domain, "--tiles", &template],
    )
    .await;
    assert_eq!(
        local.get_json("/api/map").await["tiles"]["url"],
        "/api/tiles/{z}/{x}/{y}"
    );
    assert_eq!(
        local.get("/api/tiles/3/4/2").await,
        (200, "a tile".to_owned())
    );
    assert_eq!(local.get("/api/tiles/3/4/3").await.0, 404);
    local.kill().await;

    let remote = Station::start(
        env!("CARGO_BIN_EXE_fpmo"),
        "FPMO_URL",
        &[
            "--domain",
            &domain,
            "--tiles",
            "https://tiles.example/{z}/{x}/{y}.png",
        ],
    )
    .await;
    assert_eq!(
        remote.get_json("/api/map").await["tiles"]["url"],
        "https://tiles.example/{z}/{x}/{y}.png"
    );
    assert_eq!(remote.get("/api/tiles/3/4/2").await.0, 404);
    remote.kill().await;

    // By default OpenStreetMap's tiles, with their credit; `none`: the page's grid alone.
    let default = Station::start_as_shipped(
        env!("CARGO_BIN_EXE_fpmo"),
        "FPMO_URL",
        &["--domain", &domain],
    )
    .await;
    assert_eq!(
        default.get_json("/api/map").await["tiles"],
        serde_json::json!({"url": "https://tile.openstreetmap.org/{z}/{x}/{y}.png", "minzoom": 0,
            "maxzoom": 19, "bounds": null, "attribution": "© OpenStreetMap contributors"})
    );
    default.kill().await;
    let none = Station::start(
        env!("CARGO_BIN_EXE_fpmo"),
        "FPMO_URL",
        &["--domain", &domain, "--tiles", "none"],
    )
    .await;
    assert_eq!(
        none.get_json("/api/map").await["tiles"],
        serde_json::Value::Null
    );
    none.kill().await;
}
