//! ArduPilot's family (003 §3.3.3): its mode of each flight state per vehicle and back, and
//! DO_SET_MODE to enter one. The MAVLink layer every family shares is [`super::mavlink`].

use async_trait::async_trait;
use usal_types::{FlightState, VehicleKind};

use super::{ApFamily, Arming};
use crate::mavlink_cm::{CommandError, MavlinkManager};

/// ArduPilot's [`ApFamily`]: its mode table per vehicle, modes entered with DO_SET_MODE. A
/// generic autopilot whose heartbeat shows PX4's mode encoding (MAVSDK's server) may refuse
/// the change into AUTO: its mission is started with MAV_CMD_MISSION_START.
pub struct ArduPilotModes;

#[async_trait]
impl ApFamily for ArduPilotModes {
    fn name(&self) -> &'static str {
        "ardupilot"
    }

    fn mode_for(&self, kind: VehicleKind, state: FlightState) -> Option<(&'static str, Arming)> {
        mode_for(kind, state)
    }

    fn state_for_mode(&self, kind: VehicleKind, mode: &str) -> Option<FlightState> {
        state_for_mode(kind, mode)
    }

    async fn enter(
        &self,
        mgr: &MavlinkManager,
        to: FlightState,
        mode: &'static str,
        first_slot: u16,
    ) -> Result<(), CommandError> {
        match mgr.set_mode(mode).await {
            Err(e) if to == FlightState::WaypointNavigation && mgr.state().px4_modes => {
                mgr.mission_start(first_slot).await.map_err(|_| e)
            }
            r => r,
        }
    }
}

/// The ArduPilot mode (and arming) of a flight state; `None`: no mode (CONFIGURE_CHECK, or a
/// state the vehicle does not have).
fn mode_for(kind: VehicleKind, state: FlightState) -> Option<(&'static str, Arming)> {
    use Arming::*;
    use FlightState::*;
    Some(match (kind, state) {
        (_, ConfigureCheck) => return None,
        (VehicleKind::Rover, Parking) => ("HOLD", Keep),
        (VehicleKind::Rover, Directed | Manual) => ("MANUAL", Keep),
        (VehicleKind::Rover, ManualNavigation) => ("MANUAL", Arm),
        // Driving home needs the motors, as navigating does.
        (VehicleKind::Rover, ReturnToLaunch) => ("RTL", Arm),
        (_, WaypointNavigation) => ("AUTO", Arm),
        (VehicleKind::Rover, _) => return None,
        (VehicleKind::Copter, Parking | Landing) => ("LAND", Keep),
        (VehicleKind::Copter, TakeOff) => ("GUIDED", Arm),
        // GUIDED holds where it is until given a bearing, altitude and speed (003 §3.3.1).
        (VehicleKind::Copter, Directed) => ("GUIDED", Keep),
        (VehicleKind::Copter, ManualNavigation) => ("ALT_HOLD", Arm),
        (VehicleKind::Copter, ReturnToLaunch) => ("RTL", Keep),
        (VehicleKind::Copter, Manual) => ("STABILIZE", Keep),
        (VehicleKind::Plane, Parking | Manual) => ("MANUAL", Keep),
        (VehicleKind::Plane, TakeOff) => ("TAKEOFF", Arm),
        // Steered on the ground by the station's joystick (RC override, throttle capped).
        (VehicleKind::Plane, Taxi) => ("MANUAL", Arm),
        (VehicleKind::Plane, Directed) => ("GUIDED", Keep),
        (VehicleKind::Plane, ManualNavigation) => ("FBWA", Arm),
        // A landing is a mission of its own, flown in AUTO: an approach and NAV_LAND at home
        // (the driver lays it out, `landing_mission`), as ArduPilot lands a plane.
        (VehicleKind::Plane, Landing) => ("AUTO", Keep),
        (VehicleKind::Plane, ReturnToLaunch) => ("RTL", Keep),
        (VehicleKind::Copter, Taxi) => return None,
    })
}

/// The flight state an autopilot-chosen mode means (RC switch, failsafe, end of mission).
fn state_for_mode(kind: VehicleKind, mode: &str) -> Option<FlightState> {
    use FlightState::*;
    Some(match (kind, mode) {
        (_, "AUTO") => WaypointNavigation,
        (VehicleKind::Rover, "HOLD" | "LOITER") => Parking,
        (VehicleKind::Rover, "MANUAL" | "ACRO" | "STEERING") => Directed,
        (VehicleKind::Rover, "RTL" | "SMART_RTL") => ReturnToLaunch,
        (VehicleKind::Copter, "LAND") => Landing,
        (VehicleKind::Copter, "RTL" | "SMART_RTL") => ReturnToLaunch,
        (VehicleKind::Copter, "LOITER" | "POSHOLD" | "BRAKE" | "GUIDED") => Directed,
        (VehicleKind::Copter, "STABILIZE" | "ACRO" | "ALT_HOLD") => Manual,
        (VehicleKind::Plane, "RTL") => ReturnToLaunch,
        (VehicleKind::Plane, "TAKEOFF") => TakeOff,
        (VehicleKind::Plane, "LOITER" | "CIRCLE" | "FBWA" | "FBWB" | "CRUISE" | "GUIDED") => {
            Directed
        }
        (VehicleKind::Plane, "MANUAL" | "STABILIZE" | "ACRO") => Manual,
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_rover_state_but_configure_has_a_mode() {
        for s in FlightState::ALL {
            let has = mode_for(VehicleKind::Rover, s).is_some();
            let expect = s.applies_to(VehicleKind::Rover) && s != FlightState::ConfigureCheck;
            assert_eq!(has, expect, "{s}");
        }
        assert_eq!(
            mode_for(VehicleKind::Rover, FlightState::ReturnToLaunch),
            Some(("RTL", Arming::Arm))
        );
        for kind in [VehicleKind::Copter, VehicleKind::Plane] {
            assert_eq!(
                mode_for(kind, FlightState::Directed).map(|m| m.0),
                Some("GUIDED")
            );
            for s in FlightState::ALL.into_iter().skip(1) {
                assert_eq!(
                    mode_for(kind, s).is_some(),
                    s.applies_to(kind),
                    "{kind} {s}"
                );
            }
        }
    }

    #[test]
    fn modes_map_back_to_their_states() {
        assert_eq!(
            state_for_mode(VehicleKind::Rover, "HOLD"),
            Some(FlightState::Parking)
        );
        assert_eq!(
            state_for_mode(VehicleKind::Rover, "AUTO"),
            Some(FlightState::WaypointNavigation)
        );
        assert_eq!(
            state_for_mode(VehicleKind::Copter, "LAND"),
            Some(FlightState::Landing)
        );
    }
}
