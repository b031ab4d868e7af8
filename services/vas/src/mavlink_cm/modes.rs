//! ArduPilot custom-mode numbers and names per vehicle type.

use mavlink::dialects::ardupilotmega::MavType;

const ROVER: &[(u32, &str)] = &[
    (0, "MANUAL"),
    (1, "ACRO"),
    (3, "STEERING"),
    (4, "HOLD"),
    (5, "LOITER"),
    (6, "FOLLOW"),
    (7, "SIMPLE"),
    (8, "DOCK"),
    (9, "CIRCLE"),
    (10, "AUTO"),
    (11, "RTL"),
    (12, "SMART_RTL"),
    (15, "GUIDED"),
    (16, "INITIALISING"),
];

const COPTER: &[(u32, &str)] = &[
    (0, "STABILIZE"),
    (1, "ACRO"),
    (2, "ALT_HOLD"),
    (3, "AUTO"),
    (4, "GUIDED"),
    (5, "LOITER"),
    (6, "RTL"),
    (7, "CIRCLE"),
    (9, "LAND"),
    (11, "DRIFT"),
    (13, "SPORT"),
    (14, "FLIP"),
    (15, "AUTOTUNE"),
    (16, "POSHOLD"),
    (17, "BRAKE"),
    (18, "THROW"),
    (19, "AVOID_ADSB"),
    (20, "GUIDED_NOGPS"),
    (21, "SMART_RTL"),
];

const PLANE: &[(u32, &str)] = &[
    (0, "MANUAL"),
    (1, "CIRCLE"),
    (2, "STABILIZE"),
    (3, "TRAINING"),
    (4, "ACRO"),
    (5, "FBWA"),
    (6, "FBWB"),
    (7, "CRUISE"),
    (8, "AUTOTUNE"),
    (10, "AUTO"),
    (11, "RTL"),
    (12, "LOITER"),
    (13, "TAKEOFF"),
    (14, "AVOID_ADSB"),
    (15, "GUIDED"),
    (16, "INITIALISING"),
];

/// The ArduPilot mode table for a MAVLink vehicle type (rover, copter-like or plane).
pub fn table(vehicle: MavType) -> &'static [(u32, &'static str)] {
    match vehicle {
        MavType::MAV_TYPE_GROUND_ROVER | MavType::MAV_TYPE_SURFACE_BOAT => ROVER,
        MavType::MAV_TYPE_FIXED_WING => PLANE,
        _ => COPTER,
    }
}

/// Name of a mode number.
pub fn name(vehicle: MavType, number: u32) -> Option<&'static str> {
    table(vehicle).iter().find(|m| m.0 == number).map(|m| m.1)
}

/// Number of a mode name (case-insensitive).
pub fn number(vehicle: MavType, name: &str) -> Option<u32> {
    table(vehicle)
        .iter()
        .find(|m| m.1.eq_ignore_ascii_case(name))
        .map(|m| m.0)
}

/// A mode asked for by name or by number.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ModeSpec {
    /// ArduPilot name, e.g. `"AUTO"`.
    Name(String),
    /// Custom-mode number.
    Number(u32),
}

impl From<&str> for ModeSpec {
    fn from(s: &str) -> Self {
        match s.parse() {
            Ok(n) => Self::Number(n),
            Err(_) => Self::Name(s.to_owned()),
        }
    }
}

impl From<u32> for ModeSpec {
    fn from(n: u32) -> Self {
        Self::Number(n)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_and_numbers() {
        assert_eq!(number(MavType::MAV_TYPE_GROUND_ROVER, "hold"), Some(4));
        assert_eq!(number(MavType::MAV_TYPE_GROUND_ROVER, "AUTO"), Some(10));
        assert_eq!(number(MavType::MAV_TYPE_QUADROTOR, "AUTO"), Some(3));
        assert_eq!(number(MavType::MAV_TYPE_FIXED_WING, "LOITER"), Some(12));
        assert_eq!(name(MavType::MAV_TYPE_GROUND_ROVER, 15), Some("GUIDED"));
        assert_eq!(name(MavType::MAV_TYPE_GROUND_ROVER, 2), None);
        assert_eq!(ModeSpec::from("10"), ModeSpec::Number(10));
        assert_eq!(ModeSpec::from("HOLD"), ModeSpec::Name("HOLD".into()));
    }
}
