//! Autopilot families and the mission conventions in which they differ.
//!
//! Conforming autopilots differ where the MAVLink mission protocol leaves room: ArduPilot keeps
//! home in item 0 and leaves the current item alone when a mission is uploaded; PX4 (and
//! MAVSDK's server, and most others) treat item 0 as an ordinary item and reset the current
//! item to 0 after an upload. The family comes from the heartbeat's `autopilot` field unless
//! the configuration names one.

use mavlink::dialects::ardupilotmega::MavAutopilot;

/// An autopilot family, as far as the VAS must tell them apart.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum AutopilotFamily {
    /// ArduPilot (and mavsim's default profile): item 0 is home, uploads keep the current item,
    /// ArduPilot custom-mode numbers.
    ArduPilot,
    /// PX4: item 0 is an ordinary item, uploads reset the current item to 0, custom modes are
    /// `main << 16 | sub << 24`.
    Px4,
    /// Anything else (MAVSDK's server plugins...): item 0 ordinary, uploads may reset the
    /// current item; ArduPilot mode numbers are assumed.
    #[default]
    Generic,
}

impl AutopilotFamily {
    /// The family a heartbeat's `autopilot` field names.
    pub fn from_heartbeat(autopilot: MavAutopilot) -> Self {
        match autopilot {
            MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA => Self::ArduPilot,
            MavAutopilot::MAV_AUTOPILOT_PX4 => Self::Px4,
            _ => Self::Generic,
        }
    }

    /// Item 0 of a mission is the autopilot's home, never flown to in a mission; otherwise it
    /// is an ordinary item the vehicle may drive to.
    pub fn item0_is_home(self) -> bool {
        self == Self::ArduPilot
    }

    /// A whole-mission upload leaves the current item where it was (otherwise it must be
    /// restored after every upload).
    pub fn keeps_current_on_upload(self) -> bool {
        self == Self::ArduPilot
    }

    /// The autopilot moves its current item on in the same step that reports a waypoint
    /// reached (ArduPilot's mission update, PX4's navigator), so a set-current sent after the
    /// report cannot be overtaken by that advance. Otherwise (MAVSDK's server: the
    /// application reports, then advances) a set-current waits for the advance to be reported.
    pub fn advances_with_its_report(self) -> bool {
        self != Self::Generic
    }

    /// Custom modes are PX4's (main, sub) encoding.
    pub fn px4_modes(self) -> bool {
        self == Self::Px4
    }

    /// Lower-case name, as in the configuration.
    pub fn name(self) -> &'static str {
        match self {
            Self::ArduPilot => "ardupilot",
            Self::Px4 => "px4",
            Self::Generic => "generic",
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_heartbeat_names_the_family_and_its_conventions() {
        let ap = AutopilotFamily::from_heartbeat(MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA);
        assert_eq!(ap, AutopilotFamily::ArduPilot);
        assert!(ap.item0_is_home() && ap.keeps_current_on_upload() && !ap.px4_modes());
        let px4 = AutopilotFamily::from_heartbeat(MavAutopilot::MAV_AUTOPILOT_PX4);
        assert_eq!(px4, AutopilotFamily::Px4);
        assert!(!px4.item0_is_home() && !px4.keeps_current_on_upload() && px4.px4_modes());
        let other = AutopilotFamily::from_heartbeat(MavAutopilot::MAV_AUTOPILOT_GENERIC);
        assert_eq!(other, AutopilotFamily::Generic);
        assert!(!other.item0_is_home() && !other.keeps_current_on_upload());
        assert!(ap.advances_with_its_report() && px4.advances_with_its_report());
        assert!(!other.advances_with_its_report());
    }
}
