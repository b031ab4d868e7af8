//! ArduPilot custom-mode numbers per vehicle kind and what each means to the simulator.

use crate::kinematics::VehicleKind;

/// What the simulator does in a mode.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Behaviour {
    /// Driven by RC_CHANNELS_OVERRIDE (or idle sticks).
    Manual,
    /// Stop where it is (rover, copter) or loiter (plane).
    Hold,
    /// Fly the stored mission.
    Auto,
    /// Go home, then hold.
    Rtl,
    /// Hold position until a guided target is given (a take-off, or MAV_CMD_DO_REPOSITION),
    /// then go there and hold.
    Guided,
    /// Descend where it is and disarm on the ground (copter LAND).
    Land,
    /// Climb ahead to TKOFF_ALT, then loiter (plane TAKEOFF).
    Takeoff,
}

/// One ArduPilot mode: number, name, behaviour.
pub type ModeEntry = (u32, &'static str, Behaviour);

use Behaviour::*;

const ROVER: &[ModeEntry] = &[
    (0, "MANUAL", Manual),
    (1, "ACRO", Manual),
    (3, "STEERING", Manual),
    (4, "HOLD", Hold),
    (5, "LOITER", Hold),
    (10, "AUTO", Auto),
    (11, "RTL", Rtl),
    (12, "SMART_RTL", Rtl),
    (15, "GUIDED", Guided),
    (16, "INITIALISING", Hold),
];

const COPTER: &[ModeEntry] = &[
    (0, "STABILIZE", Manual),
    (1, "ACRO", Manual),
    (2, "ALT_HOLD", Manual),
    (3, "AUTO", Auto),
    (4, "GUIDED", Guided),
    (5, "LOITER", Hold),
    (6, "RTL", Rtl),
    (9, "LAND", Land),
    (16, "POSHOLD", Hold),
    (17, "BRAKE", Hold),
    (21, "SMART_RTL", Rtl),
];

const PLANE: &[ModeEntry] = &[
    (0, "MANUAL", Manual),
    (1, "CIRCLE", Hold),
    (2, "STABILIZE", Manual),
    (5, "FBWA", Manual),
    (6, "FBWB", Manual),
    (7, "CRUISE", Manual),
    (10, "AUTO", Auto),
    (11, "RTL", Rtl),
    (12, "LOITER", Hold),
    (13, "TAKEOFF", Takeoff),
    (15, "GUIDED", Guided),
    (16, "INITIALISING", Hold),
];

/// The mode table of a vehicle kind.
pub fn table(kind: VehicleKind) -> &'static [ModeEntry] {
    match kind {
        VehicleKind::Rover => ROVER,
        VehicleKind::Copter => COPTER,
        VehicleKind::Plane => PLANE,
    }
}

/// Looks up a mode number.
pub fn lookup(kind: VehicleKind, number: u32) -> Option<ModeEntry> {
    table(kind).iter().copied().find(|m| m.0 == number)
}

/// The name of a mode number, or `"UNKNOWN"`.
pub fn name(kind: VehicleKind, number: u32) -> &'static str {
    lookup(kind, number).map_or("UNKNOWN", |m| m.1)
}

/// The mode a vehicle boots into (ArduPilot: INITIAL_MODE, MANUAL for rover/plane, STABILIZE for copter).
pub fn initial(_kind: VehicleKind) -> u32 {
    0
}

/// The mode ArduPilot enters when the mission is complete.
pub fn mission_complete(kind: VehicleKind) -> Option<u32> {
    match kind {
        // Rover: "Mission Complete" then HOLD (003 §2.5.4).
        VehicleKind::Rover => Some(4),
        // Copter stays in AUTO and hovers at the last waypoint.
        VehicleKind::Copter => None,
        // Plane: loiter at the last waypoint.
        VehicleKind::Plane => Some(12),
    }
}

/// The number of the HOLD-like mode used by tests and failsafes.
pub fn hold(kind: VehicleKind) -> u32 {
    match kind {
        VehicleKind::Rover => 4,
        VehicleKind::Copter => 5,
        VehicleKind::Plane => 12,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rover_numbers_match_ardupilot() {
        assert_eq!(name(VehicleKind::Rover, 0), "MANUAL");
        assert_eq!(name(VehicleKind::Rover, 4), "HOLD");
        assert_eq!(name(VehicleKind::Rover, 10), "AUTO");
        assert_eq!(name(VehicleKind::Rover, 15), "GUIDED");
        assert_eq!(name(VehicleKind::Rover, 99), "UNKNOWN");
        assert_eq!(
            lookup(VehicleKind::Copter, 3).map(|m| m.2),
            Some(Behaviour::Auto)
        );
    }
}
