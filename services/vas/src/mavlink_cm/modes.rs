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

/// PX4's custom modes as `main << 16 | sub << 24`, named like the ArduPilot modes the APL asks
/// for (AUTO = AUTO.MISSION, HOLD = AUTO.LOITER), PX4's own name second.
const PX4: &[(u32, &str)] = &[
    (1 << 16, "MANUAL"),
    (2 << 16, "ALTCTL"),
    (3 << 16, "POSCTL"),
    (4 << 16 | 4 << 24, "AUTO"),
    (4 << 16 | 3 << 24, "HOLD"),
    (4 << 16 | 5 << 24, "RTL"),
    (4 << 16 | 2 << 24, "TAKEOFF"),
    (4 << 16 | 6 << 24, "LAND"),
    (4 << 16 | 1 << 24, "READY"),
    (5 << 16, "ACRO"),
    (6 << 16, "OFFBOARD"),
    (7 << 16, "STABILIZED"),
];

/// Name of a PX4 custom mode.
pub fn px4_name(custom: u32) -> Option<&'static str> {
    PX4.iter().find(|m| m.0 == custom).map(|m| m.1)
}

/// PX4 custom mode of a name (case-insensitive; `LOITER` is `HOLD`, AUTO.LOITER).
pub fn px4_number(name: &str) -> Option<u32> {
    let name = if name.eq_ignore_ascii_case("LOITER") {
        "HOLD"
    } else {
        name
    };
    PX4.iter()
        .find(|m| m.1.eq_ignore_ascii_case(name))
        .map(|m| m.0)
}

/// PX4's (main, sub) of a custom mode, as MAV_CMD_DO_SET_MODE's param2 and param3.
pub fn px4_main_sub(custom: u32) -> (u8, u8) {
    (((custom >> 16) & 0xff) as u8, ((custom >> 24) & 0xff) as u8)
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

    #[test]
    fn px4_modes_encode_main_and_sub() {
        let auto = px4_number("auto").unwrap();
        assert_eq!(auto, 0x0404_0000);
        assert_eq!(px4_main_sub(auto), (4, 4));
        assert_eq!(px4_name(auto), Some("AUTO"));
        assert_eq!(px4_number("LOITER"), px4_number("HOLD"));
        assert_eq!(px4_main_sub(px4_number("MANUAL").unwrap()), (1, 0));
        assert_eq!(px4_name(0x0909_0000), None);
    }
}
