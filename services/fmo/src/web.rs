//! The FMo's HTTP side: the page (embedded, no internet resources), its JSON API and the live
//! channel, a server-sent-event stream of state snapshots. The page, the snapshot and the live
//! channel are served by `station_web` as for every station; the rest are the FMo's own.
//!
//! | method | path | body | answer |
//! |---|---|---|---|
//! | GET | `/` | | the page |
//! | GET | `/api/state` | | the snapshot ([`crate::model::Snapshot`]) |
//! | GET | `/api/events` | | SSE: `state` events carrying snapshots, at least 4 per second |
//! | POST | `/api/select` | `{"vehicle": "rover1/vas"}` | 204, or 404 |
//! | POST | `/api/change_state` | `{"to": "DIRECTED", "vehicle"?: ...}` | 202 `{"id"}`: pending, see `commands` |
//! | POST | `/api/command` | `{"command": "ARM" \| "DISARM" \| {"DIRECTED": {"alt","speed","bearing"}}, "vehicle"?: ...}` | 202 `{"id"}`: pending, see `commands` |
//! | POST | `/api/alarms/ack` | `{"id"?: 3, "vehicle"?: ...}` | `{"acked": n}` |
//! | GET | `/api/params?vehicle=...` | | the autopilot's parameters as its VAS lists them: `[{"name", "value"}]`, or 502 `{error}` |
//! | POST | `/api/params` | `{"name": "WP_SPEED", "value": 3.0, "vehicle"?: ...}` | 202 `{"id"}`: pending, see `commands` |
//! | POST | `/api/manual` | `{"roll","pitch","throttle","yaw","deadman","source"}` | 204 |

use std::sync::Arc;
use std::time::Instant;

use axum::extract::Query;
use axum::extract::State;
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use serde::Deserialize;
use station_web::error as bad;
use usal_types::{FlightState, VehicleCommand};

use crate::model::StickInput;
use crate::Shared;

impl station_web::Station for Shared {
    const PAGE: &'static str = include_str!("page.html");

    fn snapshot_json(&self) -> String {
        let now = Instant::now();
        let mut snap = self.station().snapshot(now);
        snap.replay = self.replay.view(now);
        serde_json::to_string(&snap).unwrap_or_else(|e| format!("{{\"error\":\"{e}\"}}"))
    }

    fn live(&self) -> &station_web::Live {
        &self.live
    }

    fn tiles(&self) -> Option<Arc<station_web::tiles::Tiles>> {
        self.tiles.clone()
    }
}

/// The FMo's routes.
pub fn router(shared: Arc<Shared>) -> Router {
    station_web::routes::<Shared>()
        .route("/api/select", post(select))
        .route("/api/change_state", post(change_state))
        .route("/api/command", post(command))
        .route("/api/alarms/ack", post(ack))
        .route("/api/manual", post(manual))
        .route("/api/params", get(params).post(set_param))
        .with_state(shared)
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
            shared.live.changed.notify_waiters();
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
    match commanded(&shared, c.vehicle) {
        Some(vehicle) => station_web::accepted(shared.request_state(&vehicle, to)),
        None => no_vehicle(),
    }
}

/// The vehicle a request names, else the one commanded (`None`: none heard yet).
fn commanded(shared: &Shared, vehicle: Option<String>) -> Option<String> {
    vehicle.or_else(|| shared.station().selected().map(str::to_owned))
}

fn no_vehicle() -> Response {
    bad(StatusCode::CONFLICT, "no vehicle heard yet")
}

#[derive(Deserialize)]
struct Command {
    command: serde_json::Value,
    #[serde(default)]
    vehicle: Option<String>,
}

async fn command(State(shared): State<Arc<Shared>>, Json(c): Json<Command>) -> Response {
    // The command's JSON is the VAS's own (`"ARM"`, `{"DIRECTED": {...}}`); a target that
    // cannot be flown is the VAS's to refuse, with its reason.
    let cmd: VehicleCommand = match serde_json::from_value(c.command.clone()) {
        Ok(cmd) => cmd,
        Err(e) => {
            return bad(
                StatusCode::BAD_REQUEST,
                format!(
                    "`{}` is not a command (ARM, DISARM or {{\"DIRECTED\": {{\"alt\", \"speed\", \"bearing\"}}}}): {e}",
                    c.command
                ),
            )
        }
    };
    match commanded(&shared, c.vehicle) {
        Some(vehicle) => station_web::accepted(shared.send_command(&vehicle, cmd)),
        None => no_vehicle(),
    }
}

#[derive(Deserialize)]
struct ParamsQuery {
    #[serde(default)]
    vehicle: Option<String>,
}

async fn params(State(shared): State<Arc<Shared>>, Query(q): Query<ParamsQuery>) -> Response {
    let Some(vehicle) = commanded(&shared, q.vehicle) else {
        return no_vehicle();
    };
    match shared.params(&vehicle).await {
        Ok(mut all) => {
            all.sort_by(|a, b| a.name.cmp(&b.name));
            Json(all).into_response()
        }
        Err(e) => bad(
            StatusCode::BAD_GATEWAY,
            format!("cannot list {vehicle}'s parameters: {e}"),
        ),
    }
}

#[derive(Deserialize)]
struct SetParam {
    name: String,
    value: f32,
    #[serde(default)]
    vehicle: Option<String>,
}

async fn set_param(State(shared): State<Arc<Shared>>, Json(p): Json<SetParam>) -> Response {
    // MAVLink names are at most 16 characters; the autopilot checks the rest.
    if p.name.is_empty() || p.name.len() > 16 || !p.name.is_ascii() {
        return bad(
            StatusCode::BAD_REQUEST,
            format!(
                "`{}` is not a parameter name (1 to 16 ASCII characters)",
                p.name
            ),
        );
    }
    if !p.value.is_finite() {
        return bad(StatusCode::BAD_REQUEST, "the value is not a number");
    }
    match commanded(&shared, p.vehicle) {
        Some(vehicle) => station_web::accepted(shared.set_param(
            &vehicle,
            usal_types::ParamValue {
                name: p.name,
                value: p.value,
            },
        )),
        None => no_vehicle(),
    }
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
            shared.live.changed.notify_waiters();
            Json(serde_json::json!({ "acked": n })).into_response()
        }
        Err(e) => bad(StatusCode::NOT_FOUND, e),
    }
}

async fn manual(State(shared): State<Arc<Shared>>, Json(input): Json<StickInput>) -> Response {
    shared.station().manual_input(input, Instant::now());
    StatusCode::NO_CONTENT.into_response()
}
