//! The routes every station serves the same way: its page, its snapshot and the live channel (a
//! server-sent-event stream of snapshots), plus serving a router until cancelled and the JSON
//! answers the stations' own routes share.
//!
//! | method | path | answer |
//! |---|---|---|
//! | GET | `/` | [`Station::PAGE`], `Cache-Control: no-store` |
//! | GET | `/api/state` | [`Station::snapshot_json`], `application/json` |
//! | GET | `/api/events` | SSE: `state` events carrying snapshots, at least every [`SNAPSHOT_PERIOD`] |
//! | GET | `/map.js` | the map script every station's page draws with ([`MAP_SCRIPT`]) |
//! | GET | `/api/map` | `{tiles: null \| {url, minzoom, maxzoom, bounds, attribution}}` ([`Station::tiles`]) |
//! | GET | `/api/tiles/{z}/{x}/{y}` | a tile from the station's MBTiles file or tile directory / 404 |

use std::convert::Infallible;
use std::sync::Arc;
use std::time::Duration;

use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use axum::{Json, Router};
use futures_util::stream::Stream;
use tokio_util::sync::CancellationToken;

use crate::tiles::{Tiles, TILE_ROUTE};
use crate::Live;

/// Longest interval between two snapshots on the live channel, so the page can tell a silent
/// station from a quiet vehicle.
pub const SNAPSHOT_PERIOD: Duration = Duration::from_millis(250);
/// Shortest interval between two snapshots (a burst of changes is sent as one).
pub const SNAPSHOT_MIN_GAP: Duration = Duration::from_millis(50);

/// What a station's shared state gives the common routes.
pub trait Station: Send + Sync + 'static {
    /// The page: HTML, CSS and JS in one file, compiled into the binary (no internet resources).
    const PAGE: &'static str;
    /// The page's view of everything, as JSON (`GET /api/state` and each `state` event).
    fn snapshot_json(&self) -> String;
    /// Its change notification (wakes the live channels) and cancellation (ends them).
    fn live(&self) -> &Live;
    /// The map tiles its page draws under the map (none: the page's grid alone).
    fn tiles(&self) -> Option<Arc<Tiles>> {
        None
    }
}

/// The map both stations' pages draw with (projection, tiles or the grid, fence, home,
/// numbered waypoints, vehicles, tracks, legend, scale), served at `/map.js`.
pub const MAP_SCRIPT: &str = include_str!("map.js");

/// The routes every station serves (`/`, `/api/state`, `/api/events`); the station adds its own
/// and its state.
pub fn routes<S: Station>() -> Router<Arc<S>> {
    Router::new()
        .route("/", get(page::<S>))
        .route("/api/state", get(state::<S>))
        .route("/api/events", get(events::<S>))
        .route("/map.js", get(map_script))
        .route("/api/map", get(map_config::<S>))
        .route(TILE_ROUTE, get(tile::<S>))
}

async fn map_script() -> Response {
    (
        [
            (header::CONTENT_TYPE, "text/javascript; charset=utf-8"),
            (header::CACHE_CONTROL, "no-store"),
        ],
        MAP_SCRIPT,
    )
        .into_response()
}

async fn map_config<S: Station>(State(shared): State<Arc<S>>) -> Response {
    let tiles = shared.tiles().map(|t| t.view());
    Json(serde_json::json!({ "tiles": tiles })).into_response()
}

async fn tile<S: Station>(
    State(shared): State<Arc<S>>,
    axum::extract::Path((z, x, y)): axum::extract::Path<(u32, u32, String)>,
) -> Response {
    let Some(tiles) = shared.tiles() else {
        return error(StatusCode::NOT_FOUND, "no map tiles");
    };
    // `{y}` may carry the extension a tile URL template often has (`3.png`).
    let Ok(y) = y.split('.').next().unwrap_or_default().parse::<u32>() else {
        return error(StatusCode::BAD_REQUEST, "tile row is not a number");
    };
    match tokio::task::spawn_blocking(move || tiles.tile(z, x, y)).await {
        Ok(Ok(Some((bytes, ty)))) => (
            [
                (header::CONTENT_TYPE, ty),
                (header::CACHE_CONTROL, "max-age=3600"),
            ],
            bytes,
        )
            .into_response(),
        Ok(Ok(None)) => error(StatusCode::NOT_FOUND, format!("no tile {z}/{x}/{y}")),
        Ok(Err(e)) => {
            tracing::warn!("{e}");
            error(StatusCode::INTERNAL_SERVER_ERROR, e)
        }
        Err(e) => error(
            StatusCode::INTERNAL_SERVER_ERROR,
            format!("tile reader: {e}"),
        ),
    }
}

async fn page<S: Station>() -> Response {
    ([(header::CACHE_CONTROL, "no-store")], Html(S::PAGE)).into_response()
}

async fn state<S: Station>(State(shared): State<Arc<S>>) -> Response {
    (
        [(header::CONTENT_TYPE, "application/json")],
        shared.snapshot_json(),
    )
        .into_response()
}

async fn events<S: Station>(State(shared): State<Arc<S>>) -> Response {
    snapshot_stream(shared).into_response()
}

/// An SSE stream of `state` events: a snapshot at once, then on every [`Live::changed`]
/// wake-up (at most every [`SNAPSHOT_MIN_GAP`]) and at least every [`SNAPSHOT_PERIOD`]; ends
/// when the station is cancelled.
pub fn snapshot_stream<S: Station>(
    shared: Arc<S>,
) -> Sse<impl Stream<Item = Result<Event, Infallible>>> {
    Sse::new(snapshots(shared)).keep_alive(KeepAlive::default())
}

/// The events of [`snapshot_stream`].
fn snapshots<S: Station>(shared: Arc<S>) -> impl Stream<Item = Result<Event, Infallible>> {
    futures_util::stream::unfold((shared, true), |(shared, first)| async move {
        if !first {
            let cancel = &shared.live().cancel;
            tokio::select! {
                _ = shared.live().changed.notified() => {}
                _ = tokio::time::sleep(SNAPSHOT_PERIOD) => {}
                _ = cancel.cancelled() => return None,
            }
            tokio::select! {
                _ = tokio::time::sleep(SNAPSHOT_MIN_GAP) => {}
                _ = cancel.cancelled() => return None,
            }
        }
        let json = shared.snapshot_json();
        Some((
            Ok(Event::default().event("state").data(json)),
            (shared, false),
        ))
    })
}

/// Serves `router` on `listener` until `cancel`.
///
/// # Errors
/// The server failed (accepting connections).
pub async fn serve(
    listener: tokio::net::TcpListener,
    router: Router,
    cancel: CancellationToken,
) -> anyhow::Result<()> {
    axum::serve(listener, router)
        .with_graceful_shutdown(async move { cancel.cancelled_owned().await })
        .await
        .map_err(anyhow::Error::from)
}

/// A refusal as the pages read it: `status` with `{"error": msg}`.
pub fn error(status: StatusCode, msg: impl Into<String>) -> Response {
    (status, Json(serde_json::json!({ "error": msg.into() }))).into_response()
}

/// A command started: `202 {"id": id}` (pending until the vehicle answers).
pub fn accepted(id: u64) -> Response {
    (StatusCode::ACCEPTED, Json(serde_json::json!({ "id": id }))).into_response()
}

#[cfg(test)]
mod tests {
    use super::*;
    use futures_util::StreamExt;

    struct Fake {
        live: Live,
        n: std::sync::atomic::AtomicU32,
    }

    impl Station for Fake {
        const PAGE: &'static str = "<p>page</p>";
        fn snapshot_json(&self) -> String {
            let n = self.n.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
            format!("{{\"n\":{n}}}")
        }
        fn live(&self) -> &Live {
            &self.live
        }
    }

    fn fake() -> Arc<Fake> {
        Arc::new(Fake {
            live: Live::default(),
            n: 0.into(),
        })
    }

    /// Serves the common routes of `shared` on a free port; returns its address.
    async fn served(shared: Arc<Fake>) -> std::net::SocketAddr {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let cancel = shared.live.cancel.clone();
        let router = routes::<Fake>().with_state(shared);
        tokio::spawn(serve(listener, router, cancel));
        addr
    }

    /// One HTTP/1.0 GET; the whole answer (the server closes after it).
    async fn get(addr: std::net::SocketAddr, path: &str) -> String {
        use tokio::io::{AsyncReadExt, AsyncWriteExt};
        let mut s = tokio::net::TcpStream::connect(addr).await.unwrap();
        s.write_all(format!("GET {path} HTTP/1.0\r\n\r\n").as_bytes())
            .await
            .unwrap();
        let mut out = String::new();
        s.read_to_string(&mut out).await.unwrap();
        out
    }

    #[tokio::test]
    async fn page_and_state_are_served_with_their_headers() {
        let shared = fake();
        let addr = served(shared.clone()).await;
        let limit = Duration::from_secs(10);
        let page = tokio::time::timeout(limit, get(addr, "/")).await.unwrap();
        assert!(page.starts_with("HTTP/1.0 200"), "{page}");
        assert!(page.contains("cache-control: no-store"), "{page}");
        assert!(page.ends_with("<p>page</p>"), "{page}");
        let state = tokio::time::timeout(limit, get(addr, "/api/state"))
            .await
            .unwrap();
        assert!(state.contains("content-type: application/json"), "{state}");
        assert!(state.ends_with("{\"n\":0}"), "{state}");
        shared.live.cancel.cancel();
    }

    #[tokio::test]
    async fn the_stream_sends_at_once_then_at_least_every_period_and_ends_on_cancel() {
        use std::sync::atomic::Ordering::SeqCst;
        let shared = fake();
        let mut s = Box::pin(snapshots(shared.clone()));
        let limit = Duration::from_secs(10);
        // The events are opaque; count the snapshots taken instead.
        assert!(tokio::time::timeout(limit, s.next())
            .await
            .unwrap()
            .is_some());
        assert_eq!(shared.n.load(SeqCst), 1, "the first one at once");

        let start = std::time::Instant::now();
        assert!(tokio::time::timeout(limit, s.next())
            .await
            .unwrap()
            .is_some());
        assert!(
            start.elapsed() >= SNAPSHOT_PERIOD + SNAPSHOT_MIN_GAP,
            "unprompted: a period, then the gap"
        );
        assert_eq!(shared.n.load(SeqCst), 2);

        shared.live.cancel.cancel();
        let end = tokio::time::timeout(limit, s.next()).await.unwrap();
        assert!(end.is_none(), "ends on cancel");
        assert_eq!(shared.n.load(SeqCst), 2, "no snapshot after the cancel");
    }
}
