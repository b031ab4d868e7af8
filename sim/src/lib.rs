//! mavsim: an ArduPilot-compatible MAVLink vehicle simulator.
//!
//! Layers, bottom-up:
//! - [`kinematics`]: local tangent plane and rover / copter / plane motion;
//! - [`battery`]: the battery drained by time armed and distance covered;
//! - [`mission`]: the vehicle side of the mission protocol (pure state machine);
//! - [`params`], [`modes`]: ArduPilot parameter and mode tables;
//! - [`profile`]: ArduPilot, PX4 or generic autopilot conventions (`--autopilot`);
//! - [`fence`]: the geofence (the FENCE transfer of polygon and circle items, ArduPilot's
//!   `FENCE_*` and PX4's `GF_*`, breaches; `--fence-capacity`);
//! - [`vehicle`]: the simulated autopilot (message handling, navigation, telemetry), pure;
//! - [`link`]: which transport (UDP, serial, pty) and the vehicle's frame header, over a
//!   [`mavconn::Connection`] (shared with the VAS);
//! - [`sim`]: the async driver tying a [`vehicle::Vehicle`] to a link at a speed-up factor;
//! - [`log`]: the JSON-lines event log;
//! - [`detector`]: points of interest reported when the vehicle passes them (`--poi-file`).

// ArduPilot still speaks the superseded messages (MISSION_ITEM, MISSION_REQUEST,
// SET_MODE, REQUEST_DATA_STREAM, MISSION_SET_CURRENT) and so must its simulator.
#![allow(deprecated)]

pub mod battery;
pub mod camera;
pub mod detector;
pub mod fence;
pub mod kinematics;
pub mod link;
pub mod log;
pub mod mission;
pub mod modes;
pub mod params;
pub mod profile;
pub mod sim;
pub mod vehicle;
