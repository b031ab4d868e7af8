//! The MAVLink Communication Manager (003 §3.2.2): everything the VAS needs from
//! a MAVLink autopilot, over serial, UDP or TCP, knowing nothing of USAL.
//!
//! - `manager`: [`MavlinkManager`], its configuration, state, events and commands;
//! - `driver`: the task that owns the [`mavconn::Connection`] (shared with mavsim), decodes
//!   frames into state and events, and carries the requests' messages;
//! - `param`, `mission`: the parameter and mission protocols on the manager;
//! - `mission_upload`: the mission upload as a pure state machine (`now` and messages in,
//!   messages and the next deadline out), tested on a simulated clock;
//! - `modes`, `reach`, `types`: ArduPilot mode tables, waypoint-reached detection, public types.
//!
//! ```no_run
//! # async fn demo() -> Result<(), Box<dyn std::error::Error>> {
//! use vas::mavlink_cm::{ManagerConfig, MavlinkManager, MissionItem, Telemetry};
//! let mgr = MavlinkManager::open("udpout:127.0.0.1:14560", ManagerConfig::default()).await?;
//! mgr.wait_connected(std::time::Duration::from_secs(5)).await?;
//! mgr.request_telemetry(&[(Telemetry::Position, 4.0)]).await?;
//! let home = MissionItem::waypoint(41.2757, 1.9881, 0.0);
//! mgr.mission_upload(&[home, MissionItem::waypoint(41.2760, 1.9881, 0.0)]).await?;
//! mgr.arm(true).await?;
//! mgr.set_mode("AUTO").await?;
//! let mut events = mgr.subscribe();
//! while let Ok(ev) = events.recv().await {
//!     println!("{ev:?}");
//! }
//! # Ok(()) }
//! ```

// ArduPilot still speaks the superseded messages (MISSION_ITEM, MISSION_REQUEST,
// MISSION_SET_CURRENT, REQUEST_DATA_STREAM); the manager must understand them.
#![allow(deprecated)]

mod driver;
mod family;
mod forward;
#[cfg(feature = "fuzzing")]
mod fuzz;
mod manager;
mod mission;
mod mission_upload;
mod modes;
mod outbound;
mod param;
mod reach;
mod types;

pub use family::AutopilotFamily;
/// The mission upload machine under structure-aware fuzzing (feature `fuzzing`): see the
/// `fuzz` module's docs for what is generated and checked. Panics when a property fails.
#[cfg(feature = "fuzzing")]
pub fn fuzz_mission_upload(data: &[u8]) {
    let _ = fuzz::run(data);
}

pub use manager::{ManagerConfig, MavlinkManager, Telemetry, VehicleState};
pub use mavconn::{Endpoint, EndpointParseError};
pub use modes::{
    name as mode_name, number as mode_number, px4_main_sub, px4_name, px4_number, ModeSpec,
};
pub use reach::{parse_reached_text, ReachDetector, ReachSource};
pub use types::*;

/// The MAVLink dialect the manager speaks, re-exported for callers' convenience.
pub use mavlink::dialects::ardupilotmega as dialect;
