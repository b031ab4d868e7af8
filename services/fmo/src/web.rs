//! The FMo's HTTP side: the page (embedded, no internet resources), its JSON API and the live
//! channel, a server-sent-event stream of state snapshots. The SSE helpers are public so the
//! FPMo serves its page the same way.
//!
//! | method | path | body | answer |
//! |---|---|---|---|
//! | GET | `/` | | the page |
//! | GET | `/api/state` | | the snapshot ([`crate::model::Snapshot`]) |
//! | GET | `/api/events` | | SSE: `state` events carrying snapshots, at least 4 per second |
//! | POST | `/api/select` | `{"vehicle": "rover1/vas"}` | 204, or 404 |
//! | POST | `/api/change_state` | `{"to": "DIRECTED", "vehicle"?: ...}` | 202 `{"id"}`: pending, see `commands` |
//! | POST | `/api/alarms/ack` | `{"id"?: 3, "vehicle"?: ...}` | `{"acked": n}` |
//! | POST | `/api/manual` | `{"roll","pitch","throttle","yaw","deadman","source"}` | 204 |

use std::convert::Infallible;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use futures_util::stream::Stream;
use serde::Deserialize;
use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;
use usal_types::FlightState;

use crate::model::StickInput;
use crate::Shared;

/// The page: HTML, CSS and JS in one file, compiled into the binary.
const PAGE: &str = include_str!("page.html");

/// Longest interval between two snapshots on the live channel, so the page can tell a silent
/// station from a quiet vehicle.
pub const SNAPSHOT_PERIOD: Duration = Duration::from_millis(250);
/// Shortest interval between two snapshots (a burst of changes is sent as one).
pub const SNAPSHOT_MIN_GAP: Duration = Duration::from_millis(50);

/// Prints `NAME=http://ADDR/` on stdout (the line tests and the launcher read).
pub fn print_url(name: &str, addr: SocketAddr) {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    let _ = writeln!(out, "{name}=http://{addr}/");
    let _ = out.flush();
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

/// An SSE stream of `state` events: `snapshot()` on every `changed` wake-up (at most every
/// [`SNAPSHOT_MIN_GAP`]) and at least every [`SNAPSHOT_PERIOD`]; ends at `cancel`.
pub fn snapshot_stream<S, F>(
    shared: Arc<S>,
    changed: fn(&S) -> &Notify,
    snapshot: F,
    cancel: CancellationToken,
) -> Sse<impl Stream<Item = Result<Event, Infallible>>>
where
    S: Send + Sync + 'static,
    F: Fn(&S) -> String + Send + Sync + 'static,
{
    let snapshot = Arc::new(snapshot);
    let stream =
        futures_util::stream::unfold((shared, true, cancel), move |(shared, first, cancel)| {
            let snapshot = snapshot.clone();
            async move {
                if !first {
                    tokio::select! {
                        _ = changed(&shared).notified() => {}
                        _ = tokio::time::sleep(SNAPSHOT_PERIOD) => {}
                        _ = cancel.cancelled() => return None,
                    }
                    tokio::select! {
                        _ = tokio::time::sleep(SNAPSHOT_MIN_GAP) => {}
                        _ = cancel.cancelled() => return None,
                    }
                }
                let json = snapshot(&shared);
                Some((
                    Ok(Event::default().event("state").data(json)),
                    (shared, false, cancel),
                ))
            }
        });
    Sse::new(stream).keep_alive(KeepAlive::default())
}

/// The FMo's routes.
pub fn router(shared: Arc<Shared>) -> Router {
    Router::new()
        .route("/", get(page))
        .route("/api/state", get(state))
        .route("/api/events", get(events))
        .route("/api/select", post(select))
        .route("/api/change_state", post(change_state))
        .route("/api/alarms/ack", post(ack))
        .route("/api/manual", post(manual))
        .with_state(shared)
}

async fn page() -> Response {
    ([(header::CACHE_CONTROL, "no-store")], Html(PAGE)).into_response()
}

fn snapshot_json(shared: &Shared) -> String {
    let snap = shared.station().snapshot(Instant::now());
    serde_json::to_string(&snap).unwrap_or_else(|e| format!("{{\"error\":\"{e}\"}}"))
}

async fn state(State(shared): State<Arc<Shared>>) -> Response {
    (
        [(header::CONTENT_TYPE, "application/json")],
        snapshot_json(&shared),
    )
        .into_response()
}

async fn events(State(shared): State<Arc<Shared>>) -> Response {
    let cancel = shared.cancel.clone();
    snapshot_stream(shared, |s| &s.changed, snapshot_json, cancel).into_response()
}

fn bad(status: StatusCode, msg: impl Into<String>) -> Response {
    (status, Json(serde_json::json!({ "error": msg.into() }))).into_response()
}

#[derive(Deserialize)]
struct Select {
    vehicle: String,
}

async fn select(State(shared): State<Arc<Shared>>, Json(s): Json<Select>) -> Response {
    let r = shared.station().select(&s.vehicle);
    match r {
        Ok(()) => {
            shared.refresh_allowed();
            shared.changed.notify_waiters();
            StatusCode::NO_CONTENT.into_response()
        }
        Err(e) => bad(StatusCode::NOT_FOUND, e),
    }
}

#[derive(Deserialize)]
struct ChangeState {
    to: String,
    #[serde(default)]
    vehicle: Option<String>,
}

async fn change_state(State(shared): State<Arc<Shared>>, Json(c): Json<ChangeState>) -> Response {
    let to: FlightState = match c.to.parse() {
        Ok(s) => s,
        Err(e) => return bad(StatusCode::BAD_REQUEST, e.to_string()),
    };
    let vehicle = match c.vehicle {
        Some(v) => v,
        None => match shared.station().selected() {
            Some(v) => v.to_owned(),
            None => return bad(StatusCode::CONFLICT, "no vehicle heard yet"),
        },
    };
    let id = shared.request_state(&vehicle, to);
    (StatusCode::ACCEPTED, Json(serde_json::json!({ "id": id }))).into_response()
}

#[derive(Deserialize)]
struct Ack {
    #[serde(default)]
    id: Option<u64>,
    #[serde(default)]
    vehicle: Option<String>,
}

async fn ack(State(shared): State<Arc<Shared>>, Json(a): Json<Ack>) -> Response {
    let r = shared.station().ack_alarm(a.vehicle.as_deref(), a.id);
    match r {
        Ok(n) => {
            shared.changed.notify_waiters();
            Json(serde_json::json!({ "acked": n })).into_response()
        }
        Err(e) => bad(StatusCode::NOT_FOUND, e),
    }
}

async fn manual(State(shared): State<Arc<Shared>>, Json(input): Json<StickInput>) -> Response {
    shared.station().manual_input(input, Instant::now());
    StatusCode::NO_CONTENT.into_response()
}
