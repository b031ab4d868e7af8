//! VAS: the USAL Virtual Autopilot System (work in progress).
