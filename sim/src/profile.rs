//! Autopilot profiles: how far mavsim behaves like ArduPilot, PX4 or a generic autopilot.
//!
//! The MAVLink mission protocol leaves room where conforming autopilots differ, and a ground
//! station that only ever met one of them breaks on the others:
//!
//! | | ArduPilot (default) | PX4 | generic (MAVSDK-like) | ArduPilot, resetting |
//! |---|---|---|---|---|
//! | heartbeat `autopilot` | ARDUPILOTMEGA | PX4 | GENERIC | ARDUPILOTMEGA |
//! | custom mode | ArduPilot number | `main << 16 \| sub << 24` | ArduPilot number | ArduPilot number |
//! | item 0 | home, replaced by ours | an ordinary item | an ordinary item | home |
//! | MISSION_WRITE_PARTIAL_LIST | supported | unanswered | unanswered | unanswered |
//! | current item after an upload | kept | reset to 0 | reset to 0 | reset to 0 (so 1) |
//! | MISSION_CURRENT | streamed and on change | only on change | streamed and on change | as ArduPilot |
//! | MAV_CMD_MISSION_START | unsupported | starts AUTO.MISSION | unsupported | unsupported |
//! | MAV_CMD_DO_REPOSITION | unsupported | AUTO.LOITER, go there and hold | unsupported | unsupported |
//! | geofence parameters (`fence.rs`) | `FENCE_*` | `GF_*` | `FENCE_*` | `FENCE_*` |
//!
//! The last is no autopilot's documented behaviour: a vehicle that says it is ArduPilot and
//! does not behave as one, for testing a ground station that must not trust the family alone.

use crate::kinematics::VehicleKind;
use crate::modes;

/// Which autopilot mavsim behaves like.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Profile {
    /// ArduPilot, as mavsim always was.
    #[default]
    ArduPilot,
    /// PX4's conventions.
    Px4,
    /// A generic autopilot (as MAVSDK's server plugins): ArduPilot mode numbers, PX4's mission
    /// conventions.
    Generic,
    /// Says it is ArduPilot (heartbeat, modes, item 0 home) but answers no partial write and
    /// resets its current item after every whole upload.
    ArduPilotResetting,
}

impl Profile {
    /// Item 0 is home (replaced by the vehicle's own), never flown to.
    pub fn item0_is_home(self) -> bool {
        matches!(self, Self::ArduPilot | Self::ArduPilotResetting)
    }

    /// MISSION_WRITE_PARTIAL_LIST is answered.
    pub fn partial_writes(self) -> bool {
        self == Self::ArduPilot
    }

    /// A committed whole upload resets the current item to 0.
    pub fn resets_current_on_upload(self) -> bool {
        self != Self::ArduPilot
    }

    /// MISSION_CURRENT is sent only when the current item changes (not streamed, and not in
    /// answer to a set-current that changes nothing).
    pub fn mission_current_on_change_only(self) -> bool {
        self == Self::Px4
    }

    /// The custom mode the heartbeat reports for the simulator's (ArduPilot) mode `number`.
    pub fn encode_mode(self, kind: VehicleKind, number: u32) -> u32 {
        if self != Self::Px4 {
            return number;
        }
        let (main, sub): (u32, u32) = match modes::name(kind, number) {
            "ALT_HOLD" => (2, 0),
            "POSHOLD" => (3, 0),
            "HOLD" | "LOITER" | "BRAKE" | "CIRCLE" => (4, 3),
            "AUTO" => (4, 4),
            "RTL" | "SMART_RTL" => (4, 5),
            "LAND" => (4, 6),
            "INITIALISING" => (4, 1),
            "GUIDED" => (6, 0),
            _ => (1, 0),
        };
        main << 16 | sub << 24
    }

    /// The simulator's mode for a custom mode a ground station asked for, if any.
    pub fn decode_mode(self, kind: VehicleKind, custom: u32) -> Option<u32> {
        if self != Self::Px4 {
            return Some(custom);
        }
        modes::table(kind)
            .iter()
            .map(|m| m.0)
            .find(|&n| self.encode_mode(kind, n) == custom)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn px4_modes_round_trip_and_others_are_unchanged() {
        let p = Profile::Px4;
        let rover = VehicleKind::Rover;
        assert_eq!(p.encode_mode(rover, 10), 4 << 16 | 4 << 24, "AUTO.MISSION");
        assert_eq!(p.encode_mode(rover, 4), 4 << 16 | 3 << 24, "AUTO.LOITER");
        assert_eq!(p.encode_mode(rover, 0), 1 << 16, "MANUAL");
        for n in [0, 4, 10, 11, 15] {
            assert_eq!(p.decode_mode(rover, p.encode_mode(rover, n)), Some(n));
        }
        assert_eq!(p.decode_mode(rover, 9 << 16), None);
        assert_eq!(Profile::ArduPilot.encode_mode(rover, 10), 10);
        assert_eq!(Profile::Generic.decode_mode(rover, 10), Some(10));
    }
}
