//! The vehicles' cameras in both stations: the latest frame of every camera service heard
//! (`**/camera/frame`, JPEG), served as a picture, and a point marked on it by a click, put on
//! the map with the frame's pose and sent to the fleet as a point to visit (the fleet's
//! `edit_points`, through the [`FleetView`]).
//!
//! | method | path | body | answer |
//! |---|---|---|---|
//! | GET | `/api/cameras` | | `{"cameras": [{"camera": "uav1/camera", "seq", "age_ms", "width", "height", "pose"}]}` |
//! | GET | `/api/camera/frame?camera=uav1/camera` | | the latest frame, `image/jpeg`, with `X-Frame-Seq` and `X-Frame-Age-Ms`; 404 none |
//! | POST | `/api/camera/mark` | `{"camera", "seq", "x", "y"}` (a pixel of that frame) | 200 `{"answer", "lat", "lon"}`; 404 no such frame (kept: the last 16), 400 outside the picture, 502 the fleet refused |

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use axum::extract::{Query, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use flightplan::fleet_api::PointEdit;
use serde::Deserialize;
use usal_types::camera::CameraFrame;
use usal_types::items::camera as items;

use crate::fleet::FleetView;
use crate::{error, Live};

/// Frames of a camera kept to mark a point on (the page may show one a little old).
const KEPT: usize = 16;

/// The latest frames of every camera heard, by its prefix (`uav1/camera`).
pub struct CameraView {
    fleet: Arc<FleetView>,
    latest: Mutex<BTreeMap<String, VecDeque<(CameraFrame, Instant)>>>,
}

impl CameraView {
    /// Subscribes to every camera service's frames, fed by a task of `live`; marks go to the
    /// fleet through `fleet`.
    ///
    /// # Errors
    /// The subscription cannot be declared (a stopping node).
    pub fn start(
        svc: &marea::Service,
        live: &Live,
        fleet: Arc<FleetView>,
    ) -> anyhow::Result<Arc<CameraView>> {
        let view = Arc::new(CameraView {
            fleet,
            latest: Mutex::new(BTreeMap::new()),
        });
        let sub = items::FRAME.subscribe(svc, "**/camera")?;
        let me = view.clone();
        let suffix = format!("/{}", items::FRAME.name());
        live.follow(sub, "camera frames", move |s| {
            let Some(prefix) = s.name.strip_suffix(&suffix) else {
                return;
            };
            let mut latest = marea::sync::lock(&me.latest);
            let kept = latest.entry(prefix.to_owned()).or_default();
            kept.push_back((s.value, s.received));
            while kept.len() > KEPT {
                kept.pop_front();
            }
        });
        Ok(view)
    }

    /// `GET /api/cameras`' answer.
    pub fn json(&self) -> serde_json::Value {
        let now = Instant::now();
        let cameras: Vec<serde_json::Value> = marea::sync::lock(&self.latest)
            .iter()
            .filter_map(|(camera, kept)| {
                let (f, at) = kept.back()?;
                Some(serde_json::json!({
                    "camera": camera,
                    "seq": f.seq,
                    "age_ms": crate::ms(now.saturating_duration_since(*at)),
                    "width": f.width,
                    "height": f.height,
                    "pose": f.pose,
                }))
            })
            .collect();
        serde_json::json!({ "cameras": cameras })
    }

    /// The latest frame of `camera` and how long ago it came.
    pub fn latest(&self, camera: &str) -> Option<(CameraFrame, std::time::Duration)> {
        let latest = marea::sync::lock(&self.latest);
        let (f, at) = latest.get(camera)?.back()?;
        Some((f.clone(), at.elapsed()))
    }

    /// Marks pixel `(x, y)` of frame `seq` of `camera` as a point to visit: where it is on
    /// the ground, sent to the fleet.
    ///
    /// # Errors
    /// `(status, message)`: 404 no such frame, 400 outside the picture, the fleet's own.
    pub async fn mark(
        &self,
        camera: &str,
        seq: u64,
        x: f64,
        y: f64,
    ) -> Result<(String, f64, f64), (StatusCode, String)> {
        let frame = {
            let latest = marea::sync::lock(&self.latest);
            latest
                .get(camera)
                .and_then(|kept| kept.iter().find(|(f, _)| f.seq == seq))
                .map(|(f, _)| f.clone())
        };
        let Some(f) = frame else {
            return Err((
                StatusCode::NOT_FOUND,
                format!("no frame {seq} of camera `{camera}` (the last {KEPT} are kept)"),
            ));
        };
        let Some((lat, lon)) = f.ground_point(x, y) else {
            return Err((
                StatusCode::BAD_REQUEST,
                format!("({x}, {y}) is outside the {}x{} picture", f.width, f.height),
            ));
        };
        let answer = self
            .fleet
            .edit_points(None, PointEdit::Add { lat, lon })
            .await?;
        tracing::info!("camera {camera}: point marked at {lat:.7}, {lon:.7}: {answer}");
        Ok((answer, lat, lon))
    }
}

/// The camera routes, with their state: merge into a station's router.
pub fn router(view: Arc<CameraView>) -> Router {
    Router::new()
        .route("/api/cameras", get(cameras))
        .route("/api/camera/frame", get(frame))
        .route("/api/camera/mark", post(mark))
        .with_state(view)
}

async fn cameras(State(view): State<Arc<CameraView>>) -> Response {
    Json(view.json()).into_response()
}

#[derive(Deserialize)]
struct Which {
    camera: String,
}

async fn frame(State(view): State<Arc<CameraView>>, Query(q): Query<Which>) -> Response {
    match view.latest(&q.camera) {
        Some((f, age)) if f.format == "jpeg" => (
            [
                (header::CONTENT_TYPE, "image/jpeg".to_owned()),
                (header::CACHE_CONTROL, "no-store".to_owned()),
                (
                    header::HeaderName::from_static("x-frame-seq"),
                    f.seq.to_string(),
                ),
                (
                    header::HeaderName::from_static("x-frame-age-ms"),
                    crate::ms(age).to_string(),
                ),
            ],
            f.data,
        )
            .into_response(),
        Some((f, _)) => error(
            StatusCode::NOT_FOUND,
            format!("camera `{}` sends {} frames, not jpeg", q.camera, f.format),
        ),
        None => error(
            StatusCode::NOT_FOUND,
            format!("no frame from camera `{}` yet", q.camera),
        ),
    }
}

#[derive(Deserialize)]
struct Mark {
    camera: String,
    seq: u64,
    x: f64,
    y: f64,
}

async fn mark(State(view): State<Arc<CameraView>>, Json(m): Json<Mark>) -> Response {
    match view.mark(&m.camera, m.seq, m.x, m.y).await {
        Ok((answer, lat, lon)) => {
            Json(serde_json::json!({ "answer": answer, "lat": lat, "lon": lon })).into_response()
        }
        Err((status, msg)) => error(status, msg),
    }
}
