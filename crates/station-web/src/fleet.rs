//! The fleet view both stations serve: every vehicle of a fleet mission on one map with its
//! plan, state and the detections, and a vehicle selected to command it. It reads the fleet
//! layer's one variable (`**/fleet/status`, `flightplan::fleet_api::FleetStatus`) and commands
//! through the fleet service's `pause`/`resume`, so it adds one subscription to a station,
//! whatever the number of vehicles.
//!
//! | method | path | body | answer |
//! |---|---|---|---|
//! | GET | `/fleet` | | the page (map, vehicle list, pause/resume of the selected vehicle, the points to visit: added by a click on the map, deleted, put in order) |
//! | GET | `/api/fleet` | | `{"fleets": [{"service": "gcs/fleet", "age_ms": 120, "status": FleetStatus}]}` |
//! | POST | `/api/fleet/command` | `{"vehicle": "surveyor", "action": "pause"\|"resume", "fleet"?: "gcs/fleet"}` | 200 `{"answer": "surveyor paused"}`; 400 bad action, 404 no such fleet or vehicle, 502 the fleet service refused or did not answer |
//! | POST | `/api/fleet/points` | `{"edit": PointEdit, "fleet"?: "gcs/fleet"}`: `{"Add": {"lat", "lon"}}`, `{"Delete": {"by", "id"}}`, `{"Order": {"points": [["surveyor", 3], ...]}}` | 200 `{"answer": "point #1 added at ..."}`; 404 no fleet, 502 refused (the reason: a point inside an obstacle, an unknown one) |
//!
//! The routes are guarded by the station's [`crate::Access`] like its own (the token on every
//! `/api/*` call), as they are merged into its router before serving.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use axum::extract::State;
use axum::http::{header, StatusCode};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use flightplan::fleet_api::items as fleet;
use flightplan::fleet_api::{FleetStatus, PointEdit};
use marea::Service;
use serde::Deserialize;

use crate::{call_error, error, Live};

/// The latest status of every fleet service heard, by its prefix (`gcs/fleet`).
pub struct FleetView {
    svc: Service,
    call_timeout: Duration,
    latest: Mutex<BTreeMap<String, (FleetStatus, Instant)>>,
}

impl FleetView {
    /// Subscribes to every fleet service's status, fed by a task of `live`.
    ///
    /// # Errors
    /// The subscription cannot be declared (a stopping node).
    pub fn start(
        svc: &Service,
        live: &Live,
        call_timeout: Duration,
    ) -> anyhow::Result<Arc<FleetView>> {
        let view = Arc::new(FleetView {
            svc: svc.clone(),
            call_timeout,
            latest: Mutex::new(BTreeMap::new()),
        });
        let sub = fleet::STATUS.subscribe(svc, "**/fleet")?;
        let me = view.clone();
        let suffix = format!("/{}", fleet::STATUS.name());
        live.follow(sub, "fleet status", move |s| {
            let Some(prefix) = s.name.strip_suffix(&suffix) else {
                return;
            };
            marea::sync::lock(&me.latest).insert(prefix.to_owned(), (s.value, s.received));
        });
        Ok(view)
    }

    /// `GET /api/fleet`'s answer.
    pub fn json(&self) -> serde_json::Value {
        let now = Instant::now();
        let fleets: Vec<serde_json::Value> = marea::sync::lock(&self.latest)
            .iter()
            .map(|(service, (status, at))| {
                serde_json::json!({
                    "service": service,
                    "age_ms": crate::ms(now.saturating_duration_since(*at)),
                    "status": status,
                })
            })
            .collect();
        serde_json::json!({ "fleets": fleets })
    }

    /// Pauses or resumes `vehicle` through the fleet service that has it (or `fleet`).
    ///
    /// # Errors
    /// `(status, message)`: 400 for an unknown action, 404 when no fleet has the vehicle, 502
    /// when the fleet service refuses or does not answer.
    pub async fn command(
        &self,
        fleet: Option<&str>,
        vehicle: &str,
        action: &str,
    ) -> Result<String, (StatusCode, String)> {
        let item = match action {
            "pause" => fleet::PAUSE,
            "resume" => fleet::RESUME,
            _ => {
                return Err((
                    StatusCode::BAD_REQUEST,
                    format!("action `{action}`: pause or resume"),
                ))
            }
        };
        let service = {
            let latest = marea::sync::lock(&self.latest);
            latest
                .iter()
                .find(|(name, (st, _))| {
                    fleet.is_none_or(|f| f == name.as_str())
                        && st.vehicles.iter().any(|v| v.id == vehicle)
                })
                .map(|(name, _)| name.clone())
        };
        let Some(service) = service else {
            return Err((
                StatusCode::NOT_FOUND,
                format!("no fleet has a vehicle `{vehicle}`"),
            ));
        };
        let f = item
            .function(&self.svc, &service)
            .map_err(|e| (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
        f.call(&vehicle.to_owned(), self.call_timeout)
            .await
            .map_err(|e| (StatusCode::BAD_GATEWAY, call_error(e)))
    }
}

impl FleetView {
    /// Sends an operator's edit of the points to visit to the fleet service `fleet` (or the
    /// only one heard).
    ///
    /// # Errors
    /// `(status, message)`: 404 when no fleet service is heard (or not that one), 502 when
    /// the fleet service refuses (the reason) or does not answer.
    pub async fn edit_points(
        &self,
        fleet: Option<&str>,
        edit: PointEdit,
    ) -> Result<String, (StatusCode, String)> {
        let service = {
            let latest = marea::sync::lock(&self.latest);
            latest
                .keys()
                .find(|name| fleet.is_none_or(|f| f == name.as_str()))
                .cloned()
        };
        let Some(service) = service else {
            return Err((
                StatusCode::NOT_FOUND,
                fleet.map_or("no fleet service heard".to_owned(), |f| {
                    format!("no fleet service `{f}` heard")
                }),
            ));
        };
        let f = fleet::EDIT_POINTS
            .function(&self.svc, &service)
            .map_err(|e| (StatusCode::INTERNAL_SERVER_ERROR, e.to_string()))?;
        f.call(&edit, self.call_timeout)
            .await
            .map_err(|e| (StatusCode::BAD_GATEWAY, call_error(e)))
    }
}

/// The fleet view's routes, with their state: merge into a station's router.
pub fn router(view: Arc<FleetView>) -> Router {
    Router::new()
        .route("/fleet", get(page))
        .route("/api/fleet", get(status))
        .route("/api/fleet/command", post(command))
        .route("/api/fleet/points", post(edit_points))
        .with_state(view)
}

async fn page() -> Response {
    (
        [(header::CACHE_CONTROL, "no-store")],
        Html(include_str!("fleet.html")),
    )
        .into_response()
}

async fn status(State(view): State<Arc<FleetView>>) -> Response {
    Json(view.json()).into_response()
}

#[derive(Deserialize)]
struct Command {
    vehicle: String,
    action: String,
    #[serde(default)]
    fleet: Option<String>,
}

async fn command(State(view): State<Arc<FleetView>>, Json(c): Json<Command>) -> Response {
    match view
        .command(c.fleet.as_deref(), &c.vehicle, &c.action)
        .await
    {
        Ok(answer) => Json(serde_json::json!({ "answer": answer })).into_response(),
        Err((status, msg)) => error(status, msg),
    }
}

#[derive(Deserialize)]
struct EditPoints {
    edit: PointEdit,
    #[serde(default)]
    fleet: Option<String>,
}

async fn edit_points(State(view): State<Arc<FleetView>>, Json(e): Json<EditPoints>) -> Response {
    match view.edit_points(e.fleet.as_deref(), e.edit).await {
        Ok(answer) => Json(serde_json::json!({ "answer": answer })).into_response(),
        Err((status, msg)) => error(status, msg),
    }
}
