//! VAS: the USAL Virtual Autopilot System (work in progress).
//!
//! - [`mavlink_cm`]: the MAVLink Communication Manager (003 §3.2.2), independent of USAL.

pub mod mavlink_cm;
