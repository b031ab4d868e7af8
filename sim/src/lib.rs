//! mavsim: an ArduPilot-compatible MAVLink vehicle simulator (work in progress).
