//! PX4's family: what the MAVLink layer every family shares ([`super::mavlink`]: rolling
//! queue, telemetry, reconnection) does PX4's way, [`Px4Modes`]:
//!
//! - modes are PX4's custom main/sub modes (`main << 16 | sub << 24`), named by the manager
//!   as the APL asks for them: `AUTO` is AUTO.MISSION, `HOLD` AUTO.LOITER, `RTL`
//!   AUTO.RTL, `LAND` AUTO.LAND, `TAKEOFF` AUTO.TAKEOFF, then `MANUAL`, `ALTCTL`, `POSCTL`,
//!   `STABILIZED`;
//! - WAYPOINT_NAVIGATION starts the mission with MAV_CMD_MISSION_START from the queue's
//!   current slot (DO_SET_MODE into AUTO.MISSION only where that is refused);
//! - DIRECTED is MAV_CMD_DO_REPOSITION: AUTO.LOITER where the vehicle is, after which
//!   [`IAutopilot::direct_to`] sends it elsewhere with the same command;
//! - the mission conventions (item 0 an ordinary item, no partial writes assumed, the
//!   current item reset to 0 by every whole upload and restored after it) are the manager's
//!   for [`AutopilotFamily::Px4`](crate::mavlink_cm::AutopilotFamily::Px4), which a
//!   configuration naming PX4 sets ([`super::mavlink::MavlinkAutopilot::open`]).
//!
//! Arming is the shared MAV_CMD_COMPONENT_ARM_DISARM, confirmed by the heartbeat.

use async_trait::async_trait;
use usal_types::{FlightState, VehicleKind};

use super::{ApFamily, Arming};
use crate::mavlink_cm::dialect::MavResult;
use crate::mavlink_cm::{CommandError, MavlinkManager};

/// PX4's [`ApFamily`]: mode table, MISSION_START, DO_REPOSITION.
pub struct Px4Modes;

/// The PX4 mode (manager name) and arming of a flight state.
fn px4_mode_for(kind: VehicleKind, state: FlightState) -> Option<(&'static str, Arming)> {
    use Arming::*;
    use FlightState::*;
    Some(match (kind, state) {
        (_, ConfigureCheck) => return None,
        (_, WaypointNavigation) => ("AUTO", Arm),
        // DO_REPOSITION switches to AUTO.LOITER and holds (or goes where it is sent).
        (_, Directed) => ("HOLD", Keep),
        (VehicleKind::Rover, Parking) => ("HOLD", Keep),
        (VehicleKind::Rover, ManualNavigation) => ("MANUAL", Arm),
        (VehicleKind::Rover, Manual) => ("MANUAL", Keep),
        // PX4 rovers return with AUTO.RTL as the aircraft do.
        (VehicleKind::Rover, ReturnToLaunch) => ("RTL", Keep),
        (VehicleKind::Rover, _) => return None,
        (_, Parking | Landing) => ("LAND", Keep),
        (_, TakeOff) => ("TAKEOFF", Arm),
        (_, ReturnToLaunch) => ("RTL", Keep),
        (VehicleKind::Copter, ManualNavigation) => ("ALTCTL", Arm),
        (VehicleKind::Copter, Manual) => ("STABILIZED", Keep),
        (VehicleKind::Plane, ManualNavigation) => ("STABILIZED", Arm),
        (VehicleKind::Plane, Manual) => ("MANUAL", Keep),
        (VehicleKind::Plane, Taxi) => ("MANUAL", Arm),
        (_, Taxi) => return None,
    })
}

/// The flight state a PX4 mode the autopilot chose means.
fn px4_state_for_mode(kind: VehicleKind, mode: &str) -> Option<FlightState> {
    use FlightState::*;
    Some(match (kind, mode) {
        (_, "AUTO") => WaypointNavigation,
        (VehicleKind::Rover, "HOLD") => Parking,
        (VehicleKind::Rover, "MANUAL" | "ACRO" | "STABILIZED" | "POSCTL") => Directed,
        (VehicleKind::Rover, "RTL") => ReturnToLaunch,
        (VehicleKind::Rover, _) => return None,
        (_, "HOLD" | "POSCTL") => Directed,
        (_, "LAND") => Landing,
        (_, "RTL") => ReturnToLaunch,
        (_, "TAKEOFF") => TakeOff,
        (_, "MANUAL" | "ACRO" | "STABILIZED" | "ALTCTL") => Manual,
        _ => return None,
    })
}

/// Whether a refusal means the autopilot has no such command (so another way is tried).
fn unsupported(e: &CommandError) -> bool {
    matches!(
        e,
        CommandError::Rejected {
            result: MavResult::MAV_RESULT_UNSUPPORTED,
            ..
        }
    )
}

/// Waits (one heartbeat timeout at most, as the manager's own confirmations) for the
/// heartbeat to show `mode`.
async fn confirm_mode(mgr: &MavlinkManager, mode: &'static str) -> Result<(), CommandError> {
    let mut rx = mgr.watch_state();
    let wait = mgr.heartbeat_timeout();
    let seen = tokio::time::timeout(wait, rx.wait_for(|s| s.mode_name == Some(mode)))
        .await
        .map(|r| r.map(|_| ()));
    match seen {
        Ok(Ok(())) => Ok(()),
        Ok(Err(_)) => Err(CommandError::Link(crate::mavlink_cm::LinkError::Closed)),
        Err(_) => Err(CommandError::NotConfirmed(format!("mode {mode}"))),
    }
}

#[async_trait]
impl ApFamily for Px4Modes {
    fn name(&self) -> &'static str {
        "px4"
    }

    fn mode_for(&self, kind: VehicleKind, state: FlightState) -> Option<(&'static str, Arming)> {
        px4_mode_for(kind, state)
    }

    fn state_for_mode(&self, kind: VehicleKind, mode: &str) -> Option<FlightState> {
        px4_state_for_mode(kind, mode)
    }

    async fn enter(
        &self,
        mgr: &MavlinkManager,
        to: FlightState,
        mode: &'static str,
        first_slot: u16,
    ) -> Result<(), CommandError> {
        if mgr.state().mode_name == Some(mode) && to != FlightState::Directed {
            return Ok(());
        }
        match to {
            FlightState::WaypointNavigation => match mgr.mission_start(first_slot).await {
                Err(e) if unsupported(&e) => mgr.set_mode(mode).await,
                r => r,
            },
            FlightState::Directed => {
                // Hold where it is (NaN position), in AUTO.LOITER.
                match mgr.reposition(f64::NAN, f64::NAN, f32::NAN, -1.0).await {
                    Ok(()) => confirm_mode(mgr, mode).await,
                    Err(e) if unsupported(&e) => mgr.set_mode(mode).await,
                    Err(e) => Err(e),
                }
            }
            _ => mgr.set_mode(mode).await,
        }
    }

    async fn direct_to(
        &self,
        mgr: &MavlinkManager,
        lat: f64,
        lon: f64,
        alt: f32,
        speed: f32,
    ) -> Result<(), CommandError> {
        mgr.reposition(lat, lon, alt, speed).await
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mavlink_cm::px4_number;

    #[test]
    fn every_state_has_a_px4_mode_that_maps_back() {
        for kind in [VehicleKind::Rover, VehicleKind::Copter, VehicleKind::Plane] {
            for s in FlightState::ALL {
                let m = px4_mode_for(kind, s);
                let expect = s.applies_to(kind) && s != FlightState::ConfigureCheck;
                assert_eq!(m.is_some(), expect, "{kind} {s}");
                let Some((mode, _)) = m else { continue };
                assert!(px4_number(mode).is_some(), "{mode} is a PX4 mode");
                let back = px4_state_for_mode(kind, mode);
                // HOLD is both PARKING and DIRECTED on a rover, LAND both PARKING and LANDING
                // on an aircraft: the mode alone names one of them.
                // Joystick control (RC override) does not show in the mode at all.
                let shared = matches!(
                    (kind, s),
                    (VehicleKind::Rover, FlightState::Directed)
                        | (_, FlightState::Parking | FlightState::ManualNavigation)
                        | (VehicleKind::Rover, FlightState::Manual)
                        // MANUAL, armed on the ground: the mode is the plane's MANUAL.
                        | (VehicleKind::Plane, FlightState::Taxi)
                );
                assert!(shared || back == Some(s), "{kind} {s}: {mode} -> {back:?}");
            }
        }
    }

    #[test]
    fn px4_names_its_mission_and_hold_modes_like_the_shared_layer_expects() {
        assert_eq!(
            px4_mode_for(VehicleKind::Rover, FlightState::WaypointNavigation),
            Some(("AUTO", Arming::Arm))
        );
        assert_eq!(
            px4_mode_for(VehicleKind::Copter, FlightState::Directed),
            Some(("HOLD", Arming::Keep))
        );
        assert_eq!(
            px4_state_for_mode(VehicleKind::Rover, "HOLD"),
            Some(FlightState::Parking)
        );
        assert_eq!(
            px4_state_for_mode(VehicleKind::Copter, "HOLD"),
            Some(FlightState::Directed)
        );
        assert_eq!(px4_state_for_mode(VehicleKind::Rover, "OFFBOARD"), None);
    }
}
