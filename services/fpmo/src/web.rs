//! The FPMo's HTTP side: the page, its JSON API and the SSE channel (the page, the snapshot and
//! the channel are served by `station_web`, as for every station; the rest are the FPMo's own).
//!
//! | method | path | body | answer |
//! |---|---|---|---|
//! | GET | `/` | | the page |
//! | GET | `/api/state` | | snapshot |
//! | GET | `/api/events` | | SSE `state` events carrying snapshots |
//! | GET | `/api/config` | | `{background: null \| {url, north, west, south, east}}` |
//! | GET | `/api/background` | | the background image file / 404 |
//! | GET | `/map.js`, `/api/map`, `/api/tiles/{z}/{x}/{y}` | | the map every station draws ([`station_web::http`]) |
//! | GET | `/api/plan?vehicle=rover1` | | the FPMa's plan: `{rev, version, file, name, legs, waypoints, total_points, legs_truncated}` / 404 |
//! | POST | `/api/select` | `{"vehicle"}` | 204 / 404 |
//! | POST | `/api/upload` | `{"file", "xml", "vehicle"?}` | 202 `{id}` / 400 `{error}` (checked here first) |
//! | POST | `/api/command` | `{"cmd", ..., "vehicle"?}`: `skip_leg`, `pause`, `resume`, `goto_leg {leg}`, `goto_stage {stage}`, `set_var {name, value}`, `hold_here {length?, width?, turn?}`, `exit_hold {now}`, `emergency {rule?}` | 202 `{id}` / 400 `{error}` |
//! | POST | `/api/modify_leg` | `{"leg", "changes": [["spacing", "10"]], "vehicle"?}` | 202 `{id}` |
//! | POST | `/api/retask` | `{"points": [[lat, lon]], "when": "now"\|"after", "alt"?, "vehicle"?}` | 202 `{id}` |
//! | POST | `/api/vehicle_command` | `{"command": "ARM"\|"DISARM", "vehicle"?}`: one of the vehicle's `command_offers` | 202 `{id}` / 409 `{error}` |
//! | POST | `/api/change_state` | `{"to": "WAYPOINT_NAVIGATION", "vehicle"?}`: one of the vehicle's `offers` | 202 `{id}` / 409 `{error}` (not offered from its state) |

use std::sync::Arc;

use axum::extract::{Query, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use flightplan::api::items as fpma;
use flightplan::api::{CommandAck, HoldHereArgs, HoldTurn, Retask, RetaskWhen, SetVar, VarValue};
use serde::Deserialize;
use station_web::{accepted, error as bad};

use crate::Shared;

impl station_web::Station for Shared {
    const PAGE: &'static str = include_str!("page.html");

    fn snapshot_json(&self) -> String {
        let mut snap = self.state().snapshot();
        snap["replay"] =
            serde_json::to_value(self.replay.view(std::time::Instant::now())).unwrap_or_default();
        snap.to_string()
    }

    fn live(&self) -> &station_web::Live {
        &self.live
    }

    fn tiles(&self) -> Option<Arc<station_web::tiles::Tiles>> {
        self.tiles.clone()
    }
}

/// The FPMo's routes.
pub fn router(shared: Arc<Shared>) -> Router {
    station_web::routes::<Shared>()
        .route("/api/plan", get(plan))
        .route("/api/config", get(config))
        .route("/api/background", get(background))
        .route("/api/select", post(select))
        .route("/api/upload", post(upload))
        .route("/api/command", post(command))
        .route("/api/modify_leg", post(modify))
        .route("/api/retask", post(retask))
        .route("/api/change_state", post(change_state))
        .route("/api/vehicle_command", post(vehicle_command))
        .with_state(shared)
}

async fn config(State(shared): State<Arc<Shared>>) -> Response {
    let bg = shared.background.as_ref().map(|b| b.view());
    Json(serde_json::json!({ "background": bg })).into_response()
}

async fn background(State(shared): State<Arc<Shared>>) -> Response {
    let Some(crate::background::Background {
        source: crate::background::BackgroundSource::File(path),
        ..
    }) = &shared.background
    else {
        return bad(StatusCode::NOT_FOUND, "no background image file");
    };
    match tokio::fs::read(path).await {
        Ok(bytes) => (
            [
                (header::CONTENT_TYPE, crate::background::content_type(path)),
                (header::CACHE_CONTROL, "no-cache"),
            ],
            bytes,
        )
            .into_response(),
        Err(e) => {
            tracing::warn!("background image {}: {e}", path.display());
            bad(StatusCode::NOT_FOUND, format!("background image: {e}"))
        }
    }
}

#[derive(Deserialize)]
struct PlanQuery {
    vehicle: Option<String>,
}

async fn plan(State(shared): State<Arc<Shared>>, Query(q): Query<PlanQuery>) -> Response {
    let label = match shared.target(q.vehicle) {
        Ok(l) => l,
        Err(e) => return bad(StatusCode::NOT_FOUND, e),
    };
    match shared.state().plan_view(&label) {
        Some(p) => Json(p).into_response(),
        None => bad(
            StatusCode::NOT_FOUND,
            format!("no plan known for `{label}`"),
        ),
    }
}

#[derive(Deserialize)]
struct Select {
    vehicle: String,
}

async fn select(State(shared): State<Arc<Shared>>, Json(s): Json<Select>) -> Response {
    match shared.select(&s.vehicle) {
        Ok(()) => {
            shared.live.changed.notify_waiters();
            StatusCode::NO_CONTENT.into_response()
        }
        Err(e) => bad(StatusCode::NOT_FOUND, e),
    }
}

#[derive(Deserialize)]
struct Upload {
    file: String,
    xml: String,
    #[serde(default)]
    vehicle: Option<String>,
}

async fn upload(State(shared): State<Arc<Shared>>, Json(u): Json<Upload>) -> Response {
    let label = match shared.target(u.vehicle) {
        Ok(l) => l,
        Err(e) => return bad(StatusCode::CONFLICT, e),
    };
    match shared.upload(&label, &u.file, &u.xml) {
        Ok(id) => accepted(id),
        Err(e) => bad(StatusCode::BAD_REQUEST, e),
    }
}

/// `POST /api/command`: one of the FPMa's run-time commands and its arguments.
#[derive(Deserialize)]
struct Command {
    cmd: String,
    /// `goto_leg`.
    #[serde(default)]
    leg: Option<String>,
    /// `goto_stage`: `takeoff`, `departure`, `mission`, `approach`, `landing`.
    #[serde(default)]
    stage: Option<String>,
    /// `set_var`: the variable.
    #[serde(default)]
    name: Option<String>,
    /// `set_var`: a boolean or a number.
    #[serde(default)]
    value: Option<serde_json::Value>,
    /// `exit_hold`: at once (else at the next fix crossing).
    #[serde(default)]
    now: bool,
    /// `hold_here`: straight-leg length and width, metres; turn `L` or `R`.
    #[serde(default)]
    length: Option<f64>,
    #[serde(default)]
    width: Option<f64>,
    #[serde(default)]
    turn: Option<String>,
    /// `emergency`: the rule (none: the default reaction).
    #[serde(default)]
    rule: Option<String>,
    #[serde(default)]
    vehicle: Option<String>,
}

fn ack_text(_: &mut crate::State, a: &CommandAck) -> String {
    format!(
        "version {}, leg {}",
        a.version,
        a.leg.as_deref().unwrap_or("none")
    )
}

/// A positive finite length in metres, if given.
fn metres(what: &str, v: Option<f64>) -> Result<Option<f64>, String> {
    match v {
        Some(m) if !(m.is_finite() && m > 0.0) => Err(format!("{what} must be a positive length")),
        v => Ok(v),
    }
}

async fn command(State(shared): State<Arc<Shared>>, Json(c): Json<Command>) -> Response {
    let label = match shared.target(c.vehicle.clone()) {
        Ok(l) => l,
        Err(e) => return bad(StatusCode::CONFLICT, e),
    };
    match start_command(&shared, &label, c) {
        Ok(id) => accepted(id),
        Err(e) => bad(StatusCode::BAD_REQUEST, e),
    }
}

/// Checks the arguments of `c` and starts it (pending until the FPMa answers).
fn start_command(shared: &Arc<Shared>, label: &str, c: Command) -> Result<u64, String> {
    let id = match c.cmd.as_str() {
        "skip_leg" => shared.command(label, fpma::SKIP_LEG, "skip_leg".into(), (), ack_text),
        "pause" => shared.command(label, fpma::PAUSE, "pause".into(), (), ack_text),
        "resume" => shared.command(label, fpma::RESUME, "resume".into(), (), ack_text),
        "goto_leg" => {
            let leg = c.leg.ok_or("goto_leg needs `leg`")?;
            shared.command(
                label,
                fpma::GOTO_LEG,
                format!("goto_leg {leg}"),
                leg,
                ack_text,
            )
        }
        "goto_stage" => {
            let stage = c.stage.ok_or("goto_stage needs `stage`")?;
            let what = format!("goto_stage {stage}");
            shared.command(label, fpma::GOTO_STAGE, what, stage, ack_text)
        }
        "set_var" => {
            let name = c
                .name
                .filter(|n| !n.is_empty())
                .ok_or("set_var needs `name`")?;
            let value = match c.value {
                Some(serde_json::Value::Bool(b)) => VarValue::Bool(b),
                Some(serde_json::Value::Number(n)) => match n.as_f64() {
                    Some(x) if x.is_finite() => VarValue::Number(x),
                    _ => return Err("set_var: the number is out of range".into()),
                },
                _ => return Err("set_var needs a boolean or numeric `value`".into()),
            };
            let what = match value {
                VarValue::Bool(b) => format!("set_var {name} = {b}"),
                VarValue::Number(x) => format!("set_var {name} = {x}"),
            };
            shared.command(label, fpma::SET_VAR, what, SetVar { name, value }, ack_text)
        }
        "hold_here" => {
            let turn = match c.turn.as_deref() {
                None | Some("R" | "r") => HoldTurn::Right,
                Some("L" | "l") => HoldTurn::Left,
                Some(t) => return Err(format!("hold_here: unknown turn `{t}` (L or R)")),
            };
            let args = HoldHereArgs {
                length: metres("length", c.length)?,
                width: metres("width", c.width)?,
                turn,
                ..HoldHereArgs::default()
            };
            shared.command(label, fpma::HOLD_HERE, "hold_here".into(), args, ack_text)
        }
        "exit_hold" => {
            let what = if c.now {
                "exit_hold now"
            } else {
                "exit_hold at the fix"
            };
            shared.command(label, fpma::EXIT_HOLD, what.into(), c.now, ack_text)
        }
        "emergency" => {
            let what = match &c.rule {
                Some(r) => format!("emergency {r}"),
                None => "emergency (default reaction)".into(),
            };
            shared.command(label, fpma::EMERGENCY, what, c.rule, ack_text)
        }
        other => return Err(format!("unknown command `{other}`")),
    };
    Ok(id)
}

#[derive(Deserialize)]
struct Modify {
    leg: String,
    changes: Vec<(String, String)>,
    #[serde(default)]
    vehicle: Option<String>,
}

async fn modify(State(shared): State<Arc<Shared>>, Json(m): Json<Modify>) -> Response {
    let label = match shared.target(m.vehicle) {
        Ok(l) => l,
        Err(e) => return bad(StatusCode::CONFLICT, e),
    };
    if m.changes.is_empty() {
        return bad(StatusCode::BAD_REQUEST, "no change given");
    }
    accepted(crate::modify_leg(&shared, &label, m.leg, m.changes))
}

#[derive(Deserialize)]
struct RetaskReq {
    points: Vec<(f64, f64)>,
    #[serde(default)]
    when: Option<String>,
    #[serde(default)]
    alt: Option<f64>,
    #[serde(default)]
    vehicle: Option<String>,
}

async fn retask(State(shared): State<Arc<Shared>>, Json(r): Json<RetaskReq>) -> Response {
    let label = match shared.target(r.vehicle) {
        Ok(l) => l,
        Err(e) => return bad(StatusCode::CONFLICT, e),
    };
    if r.points.is_empty()
        || r.points.iter().any(|(la, lo)| {
            !(la.is_finite() && lo.is_finite() && la.abs() <= 90.0 && lo.abs() <= 180.0)
        })
    {
        return bad(
            StatusCode::BAD_REQUEST,
            "points must be 1 or more valid (lat, lon)",
        );
    }
    let when = match r.when.as_deref() {
        None | Some("now") => RetaskWhen::Now,
        Some("after") => RetaskWhen::AfterCurrentLeg,
        Some(w) => return bad(StatusCode::BAD_REQUEST, format!("unknown `when` {w}")),
    };
    let what = format!("retask {} point(s) {:?}", r.points.len(), when);
    let args = Retask {
        points: r.points,
        alt: r.alt,
        when,
    };
    accepted(shared.command(&label, fpma::RETASK, what, args, ack_text))
}

#[derive(Deserialize)]
struct ChangeState {
    to: String,
    #[serde(default)]
    vehicle: Option<String>,
}

/// `POST /api/change_state`: a flight-state change the VAS offers (the `Start` button is
/// WAYPOINT_NAVIGATION with a plan ready).
async fn change_state(State(shared): State<Arc<Shared>>, Json(c): Json<ChangeState>) -> Response {
    let label = match shared.target(c.vehicle) {
        Ok(l) => l,
        Err(e) => return bad(StatusCode::CONFLICT, e),
    };
    let to: usal_types::FlightState = match c.to.parse() {
        Ok(s) => s,
        Err(e) => return bad(StatusCode::BAD_REQUEST, e.to_string()),
    };
    match shared.change_state(&label, to) {
        Ok(id) => accepted(id),
        Err(e) => bad(StatusCode::CONFLICT, e),
    }
}

#[derive(Deserialize)]
struct VehicleCommandReq {
    command: String,
    #[serde(default)]
    vehicle: Option<String>,
}

/// `POST /api/vehicle_command`: ARM or DISARM, when the VAS offers it.
async fn vehicle_command(
    State(shared): State<Arc<Shared>>,
    Json(c): Json<VehicleCommandReq>,
) -> Response {
    let label = match shared.target(c.vehicle) {
        Ok(l) => l,
        Err(e) => return bad(StatusCode::CONFLICT, e),
    };
    match shared.vehicle_command(&label, &c.command) {
        Ok(id) => accepted(id),
        Err(e) => bad(StatusCode::CONFLICT, e),
    }
}
