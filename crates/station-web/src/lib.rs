//! What the USAL ground stations served as web pages (the FMo and the FPMo) share: everything
//! but their model and their own routes.
//!
//! - [`startup`]: the command-line options both take ([`StationArgs`]), their configuration
//!   ([`StationConfig`]), tracing, binding the HTTP listener and printing the
//!   `NAME=http://ADDR/?token=TOKEN` line tests and the launcher read, opening the station's middleware node, and serving until
//!   cancelled then stopping in order ([`serve_and_shut_down`]).
//! - [`http`]: the [`Station`] trait a station's shared state implements, and the routes it gets
//!   from it: the page (`GET /`), its snapshot (`GET /api/state`) and the live channel
//!   (`GET /api/events`, server-sent `state` events); the JSON error and `202 {id}` answers.
//! - [`live`]: what the station's tasks and pages share ([`Live`]): the change notification,
//!   the cancellation, the tasks, and the loop feeding the station from a subscription.
//! - [`access`]: who may use a station ([`Access`]): the random token of its URL, required on
//!   every `/api/*` call, the `Host` allowlist and the `Origin` check.
//! - [`commands`]: the commands a station has sent, pending until the vehicle answers
//!   ([`CommandLog`]), and how the page sees them.
//! - [`tiles`]: the map tiles under every station's map ([`tiles::Tiles`]; OpenStreetMap's by
//!   default), and the map script both pages draw with (`GET /map.js`, `GET /api/map`,
//!   `GET /api/tiles/{z}/{x}/{y}`).
//! - [`fleet`]: the fleet view (`/fleet`, `/api/fleet`): every vehicle of a fleet mission on
//!   one map with its plan, state and detections, from the fleet layer's status.
//!
//! ```no_run
//! # use std::sync::Arc;
//! # struct Shared { live: station_web::Live }
//! impl station_web::Station for Shared {
//!     const PAGE: &'static str = "<!doctype html><title>station</title>";
//!     fn snapshot_json(&self) -> String { "{}".into() }
//!     fn live(&self) -> &station_web::Live { &self.live }
//! }
//! # async fn f(shared: Arc<Shared>) -> anyhow::Result<()> {
//! let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await?;
//! let cancel = shared.live.cancel.clone();
//! let router = station_web::routes::<Shared>().with_state(shared);
//! station_web::serve(listener, router, cancel).await
//! # }
//! ```

pub mod access;
pub mod camera;
pub mod commands;
pub mod fleet;
pub mod http;
pub mod live;
pub mod replay;
pub mod startup;
pub mod tiles;

pub use access::Access;
pub use commands::{CommandLog, CommandStatus, CommandView};
pub use http::{accepted, error, routes, serve, snapshot_stream, Station};
pub use live::Live;
pub use startup::{
    bind, call_error, init_tracing, open_node, serve_and_shut_down, Listener, StationArgs,
    StationConfig,
};

/// A duration in whole milliseconds, as the pages show ages (saturating).
pub fn ms(d: std::time::Duration) -> u64 {
    u64::try_from(d.as_millis()).unwrap_or(u64::MAX)
}
