//! The PX4 autopilot layer: the MAVLink layer every family shares (rolling queue, telemetry,
//! reconnection; see [`super::ardupilot`]) with PX4's part, [`Px4Modes`]:
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
//!   for [`AutopilotFamily::Px4`](crate::mavlink_cm::AutopilotFamily::Px4), which [`Px4::open`]
//!   configures.
//!
//! Arming is the shared MAV_CMD_COMPONENT_ARM_DISARM, confirmed by the heartbeat.

use async_trait::async_trait;
use tokio::sync::broadcast;
use usal_types::{
    AutopilotStatus, FlightState, ManualControl, QueueStatus, VehicleCommand, VehicleKind, Waypoint,
};

use super::ardupilot::{ArduPilot, ArduPilotConfig, ArduPilotOpenError};
use super::{ApEvent, ApFamily, Arming, AutopilotError, IAutopilot};
use crate::mavlink_cm::dialect::MavResult;
use crate::mavlink_cm::{AutopilotFamily, CommandError, MavlinkManager};

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

/// The PX4 implementation of [`IAutopilot`]: the shared MAVLink layer with [`Px4Modes`] and
/// the manager set to PX4's mission conventions, whatever the heartbeat says.
pub struct Px4 {
    layer: ArduPilot,
}

impl Px4 {
    /// Opens the MAVLink endpoint and starts the layer; call [`IAutopilot::listen_ap`] next.
    ///
    /// # Errors
    /// A malformed endpoint or queue size.
    pub async fn open(
        endpoint: &str,
        mut cfg: ArduPilotConfig,
    ) -> Result<Self, ArduPilotOpenError> {
        cfg.manager.family = Some(AutopilotFamily::Px4);
        let layer = ArduPilot::open_with(endpoint, cfg, Some(&Px4Modes)).await?;
        Ok(Self { layer })
    }

    /// The MAVLink manager underneath (parameters, raw commands).
    pub fn manager(&self) -> &MavlinkManager {
        self.layer.manager()
    }
}

#[async_trait]
impl IAutopilot for Px4 {
    fn vehicle(&self) -> VehicleKind {
        self.layer.vehicle()
    }

    fn events(&self) -> broadcast::Receiver<ApEvent> {
        self.layer.events()
    }

    fn status(&self) -> AutopilotStatus {
        self.layer.status()
    }

    async fn listen_ap(&self) -> Result<(), AutopilotError> {
        self.layer.listen_ap().await
    }

    async fn change_state(&self, to: FlightState) -> Result<(), AutopilotError> {
        self.layer.change_state(to).await
    }

    async fn push_waypoints(&self, wps: Vec<Waypoint>) -> Result<QueueStatus, AutopilotError> {
        self.layer.push_waypoints(wps).await
    }

    async fn clear_waypoints(&self) -> Result<QueueStatus, AutopilotError> {
        self.layer.clear_waypoints().await
    }

    async fn queue_status(&self) -> Result<QueueStatus, AutopilotError> {
        self.layer.queue_status().await
    }

    async fn manual_navigation(&self, mc: Option<ManualControl>) -> Result<(), AutopilotError> {
        self.layer.manual_navigation(mc).await
    }

    async fn direct_to(
        &self,
        lat: f64,
        lon: f64,
        alt: f32,
        speed: f32,
    ) -> Result<(), AutopilotError> {
        self.layer.direct_to(lat, lon, alt, speed).await
    }

    async fn command(&self, cmd: VehicleCommand) -> Result<(), AutopilotError> {
        self.layer.command(cmd).await
    }

    async fn upload_fence(&self, fence: Option<&usal_types::Fence>) -> Result<(), AutopilotError> {
        self.layer.upload_fence(fence).await
    }

    async fn get_param(&self, name: &str) -> Result<f32, AutopilotError> {
        self.layer.get_param(name).await
    }

    async fn set_param(&self, name: &str, value: f32) -> Result<f32, AutopilotError> {
        self.layer.set_param(name, value).await
    }

    async fn list_params(&self) -> Result<Vec<(String, f32)>, AutopilotError> {
        self.layer.list_params().await
    }

    async fn read_mission(&self, first: u16, last: u16) -> Result<Vec<Waypoint>, AutopilotError> {
        self.layer.read_mission(first, last).await
    }

    async fn shutdown(&self) {
        self.layer.shutdown().await;
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
