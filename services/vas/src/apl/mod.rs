//! The Autopilot Layer (APL, 003 §3.3): the [`IAutopilot`] interface the VAL drives, and its
//! implementation on the MAVLink manager, [`mavlink::MavlinkAutopilot`], for ArduPilot
//! ([`ardupilot`]) and PX4 ([`px4`]).
//!
//! The families share everything but their modes and how a state is entered: the MAVLink
//! layer in [`mavlink`] (rolling queue, telemetry, reconnection, the mission conventions the
//! manager applies per [`AutopilotFamily`]) takes an [`ApFamily`], the family-specific part:
//! the mode of each flight state and back, and the commands that enter a state (ArduPilot:
//! DO_SET_MODE; PX4: MAV_CMD_MISSION_START into a mission, MAV_CMD_DO_REPOSITION for
//! DIRECTED). With `autopilot="auto"` the family is read from the heartbeat each time it is
//! needed, so a replaced autopilot is met with its own table ([`family_modes`]).
//!
//! The seed's interface had 14 procedures, of which a rover needs four (003 §3.3.1):
//! `ListenAp` ([`IAutopilot::listen_ap`]), `ChangeState` ([`IAutopilot::change_state`]),
//! `ClearAllWp` ([`IAutopilot::clear_waypoints`]) and `ManualNavigation`
//! ([`IAutopilot::manual_navigation`]); pushing waypoints is how the VAL feeds the queue.
//! What the autopilot reports comes back as [`ApEvent`]s.

pub mod ardupilot;
pub mod mavlink;
pub mod px4;
pub mod queue;

use async_trait::async_trait;
use tokio::sync::broadcast;
use usal_types::{
    Alarm, Attitude, AutopilotStatus, Battery, FlightState, ManualControl, MissionChanged,
    Position, QueueStatus, Speeds, VehicleCommand, VehicleKind, Waypoint, WaypointReached,
};

pub use queue::{QueueAction, QueueCreateError, RollingQueue};

use crate::mavlink_cm::{AutopilotFamily, CommandError, MavlinkManager};

/// Whether entering a flight state arms the motors.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Arming {
    /// Leave the arming as it is.
    Keep,
    /// Arm first.
    Arm,
}

/// The family-specific part of a MAVLink autopilot layer: modes and the commands that enter
/// a flight state. Everything else (queue, telemetry, mission protocol) is shared.
#[async_trait]
pub trait ApFamily: Send + Sync {
    /// Lower-case family name, as in the configuration.
    fn name(&self) -> &'static str;

    /// The mode (as the manager names it) and arming of a flight state; `None`: no mode
    /// (CONFIGURE_CHECK, or a state the vehicle does not have).
    fn mode_for(&self, kind: VehicleKind, state: FlightState) -> Option<(&'static str, Arming)>;

    /// The flight state a mode the autopilot chose means (RC switch, failsafe, end of mission).
    fn state_for_mode(&self, kind: VehicleKind, mode: &str) -> Option<FlightState>;

    /// Puts the autopilot into `mode`, the mode of `to` (already armed where
    /// [`Self::mode_for`] says so; for WAYPOINT_NAVIGATION the queue is primed and its current
    /// slot is `first_slot`). Returns once the autopilot confirmed it.
    ///
    /// # Errors
    /// Refused, unanswered or not confirmed.
    async fn enter(
        &self,
        mgr: &MavlinkManager,
        to: FlightState,
        mode: &'static str,
        first_slot: u16,
    ) -> Result<(), CommandError>;

    /// Sends the vehicle, in DIRECTED, to (`lat`, `lon`, `alt` metres above home; NaN: keep)
    /// at `speed` m/s (≤ 0: its default), where it then holds.
    ///
    /// # Errors
    /// [`CommandError::Rejected`] where the family has no such command, else as the command.
    async fn direct_to(
        &self,
        mgr: &MavlinkManager,
        lat: f64,
        lon: f64,
        alt: f32,
        speed: f32,
    ) -> Result<(), CommandError> {
        let _ = (mgr, lat, lon, alt, speed);
        Err(CommandError::Rejected {
            command: crate::mavlink_cm::dialect::MavCmd::MAV_CMD_DO_REPOSITION,
            result: crate::mavlink_cm::dialect::MavResult::MAV_RESULT_UNSUPPORTED,
        })
    }
}

/// The family-specific part for an autopilot family: PX4's for PX4, ArduPilot's otherwise
/// (a generic autopilot such as MAVSDK's server uses ArduPilot's mode names, in whichever
/// encoding its heartbeat shows).
pub fn family_modes(family: AutopilotFamily) -> &'static dyn ApFamily {
    match family {
        AutopilotFamily::Px4 => &px4::Px4Modes,
        AutopilotFamily::ArduPilot | AutopilotFamily::Generic => &ardupilot::ArduPilotModes,
    }
}

/// What an autopilot layer reports to the VAL.
#[derive(Clone, Debug, PartialEq)]
pub enum ApEvent {
    /// Position telemetry.
    Position(Position),
    /// The autopilot's home (HOME_POSITION), at connection and after each arming.
    Home(usal_types::Home),
    /// An on-board detector reported a point of interest (its STATUSTEXT, read back).
    Detection(usal_types::PoiDetection),
    /// Attitude telemetry.
    Attitude(Attitude),
    /// Speeds telemetry.
    Speeds(Speeds),
    /// Battery state.
    Battery(Battery),
    /// Heartbeat-derived status (sent on every change and periodically).
    Status(AutopilotStatus),
    /// A waypoint of the queue was reached.
    WaypointReached(WaypointReached),
    /// Something the ground should know.
    Alarm(Alarm),
    /// The autopilot changed mode by itself (RC switch, failsafe, end of mission): the
    /// flight state the VAL should now be in, with the mode name.
    ModeChanged {
        /// The autopilot's mode name.
        mode: String,
        /// The flight state that mode means for this vehicle.
        state: Option<FlightState>,
    },
    /// An aircraft that was flying is disarmed: it landed (a mission's NAV_LAND, a LAND,
    /// an RTL that ends on the ground). A pilot sees it parked only now.
    Landed,
    /// The autopilot is configured and ready (CONFIGURE_CHECK is over).
    Configured,
    /// Another ground station changed the mission on the autopilot: the queue stopped
    /// feeding it (what was queued stays queued for a later WAYPOINT_NAVIGATION).
    MissionChanged(MissionChanged),
    /// Heartbeats stopped.
    LinkLost,
    /// Heartbeats again; the layer re-read the parameters and the mission and resumed.
    LinkRestored,
}

/// Errors of the autopilot layer.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum AutopilotError {
    /// No autopilot answers.
    #[error("autopilot not connected: {0}")]
    NotConnected(String),
    /// This autopilot cannot do it (e.g. a state with no mode for this vehicle).
    #[error("not supported by this autopilot: {0}")]
    Unsupported(String),
    /// The autopilot refused or did not confirm.
    #[error("autopilot refused: {0}")]
    Refused(String),
    /// The layer is shut down.
    #[error("autopilot layer stopped")]
    Stopped,
    /// A push would queue more waypoints than allowed: refused whole.
    #[error("{queued} queued + {pushed} pushed = {total} waypoints: at most {max} queued")]
    QueueFull {
        /// Waypoints queued before the push.
        queued: u64,
        /// Waypoints pushed.
        pushed: u64,
        /// What they would make.
        total: u64,
        /// The most the queue may hold.
        max: u64,
    },
}

/// Whether `pushed` more waypoints fit in a queue holding `queued`, `max` at most.
///
/// # Errors
/// [`AutopilotError::QueueFull`].
pub fn check_room(queued: u64, pushed: usize, max: u64) -> Result<(), AutopilotError> {
    let pushed = pushed as u64;
    let total = queued.saturating_add(pushed);
    if total > max {
        return Err(AutopilotError::QueueFull {
            queued,
            pushed,
            total,
            max,
        });
    }
    Ok(())
}

/// The APL interface (003 §3.3.1, figure 3.5), implemented per autopilot family.
#[async_trait]
pub trait IAutopilot: Send + Sync {
    /// The vehicle kind this layer drives.
    fn vehicle(&self) -> VehicleKind;

    /// Every event from now on.
    fn events(&self) -> broadcast::Receiver<ApEvent>;

    /// The latest autopilot status.
    fn status(&self) -> AutopilotStatus;

    /// `ListenAp`: waits for the autopilot, reads its parameters, sets the telemetry rates and
    /// configures it. [`ApEvent::Configured`] follows on success.
    ///
    /// # Errors
    /// No autopilot within the connection wait.
    async fn listen_ap(&self) -> Result<(), AutopilotError>;

    /// `ChangeState`: puts the autopilot in the mode (and arming) of `to`. The VAL has
    /// already checked the transition table. Entering WAYPOINT_NAVIGATION primes the rolling
    /// queue on the autopilot before switching to automatic mode.
    ///
    /// # Errors
    /// No mode for `to`, or the autopilot refused.
    async fn change_state(&self, to: FlightState) -> Result<(), AutopilotError>;

    /// Appends waypoints to the queue (after `clear_waypoints`, replaces what follows the
    /// current target), unless the queue would then hold more than `max_queued`: the room is
    /// checked and the waypoints queued in one step, so pushes side by side cannot overfill it.
    ///
    /// # Errors
    /// [`AutopilotError::QueueFull`], waypoints this autopilot cannot fly, or the layer is
    /// stopped.
    async fn push_waypoints(
        &self,
        wps: Vec<Waypoint>,
        max_queued: u64,
    ) -> Result<QueueStatus, AutopilotError>;

    /// `ClearAllWp`: "a new queue follows" (003 §6.2.2); the autopilot keeps navigating.
    ///
    /// # Errors
    /// Only when the layer is stopped.
    async fn clear_waypoints(&self) -> Result<QueueStatus, AutopilotError>;

    /// The queue as it is.
    ///
    /// # Errors
    /// Only when the layer is stopped.
    async fn queue_status(&self) -> Result<QueueStatus, AutopilotError>;

    /// `ManualNavigation`: joystick values to the actuators; `None` gives control back to the
    /// RC transmitter.
    ///
    /// # Errors
    /// Not connected.
    async fn manual_navigation(&self, mc: Option<ManualControl>) -> Result<(), AutopilotError>;

    /// A command that is not a state change (ARM, DISARM, DIRECTED with its target). The VAL
    /// has already checked it; a DIRECTED command from another state enters DIRECTED first.
    /// An autopilot layer without them refuses them all (the default).
    ///
    /// # Errors
    /// Unsupported, or the autopilot refused.
    async fn command(&self, cmd: VehicleCommand) -> Result<(), AutopilotError> {
        Err(AutopilotError::Unsupported(format!(
            "{cmd} is not implemented for this autopilot"
        )))
    }

    /// In DIRECTED: sends the vehicle to (`lat`, `lon`, `alt` metres above home; NaN: keep)
    /// at `speed` m/s (≤ 0: its default), where it holds (PX4: MAV_CMD_DO_REPOSITION).
    ///
    /// # Errors
    /// Not in DIRECTED, or the autopilot cannot (the default) or refused.
    async fn direct_to(
        &self,
        lat: f64,
        lon: f64,
        alt: f32,
        speed: f32,
    ) -> Result<(), AutopilotError> {
        let _ = (lat, lon, alt, speed);
        Err(AutopilotError::Unsupported(
            "a DIRECTED target on this autopilot".into(),
        ))
    }

    /// Reads parameter `name` from the autopilot.
    ///
    /// # Errors
    /// Unsupported, not connected, or no such parameter.
    async fn get_param(&self, name: &str) -> Result<f32, AutopilotError> {
        let _ = name;
        Err(AutopilotError::Unsupported("parameters".into()))
    }

    /// Sets parameter `name` and checks the autopilot took it; returns the value it holds.
    ///
    /// # Errors
    /// Unsupported, not connected, no such parameter, or another value reported back.
    async fn set_param(&self, name: &str, value: f32) -> Result<f32, AutopilotError> {
        let _ = (name, value);
        Err(AutopilotError::Unsupported("parameters".into()))
    }

    /// Mission items `first..=last` as the autopilot holds them now (a partial read; item 0
    /// is ArduPilot's home), `seq` their index.
    ///
    /// # Errors
    /// Unsupported, not connected, a range past the mission's end, or no answer.
    async fn read_mission(&self, first: u16, last: u16) -> Result<Vec<Waypoint>, AutopilotError> {
        let _ = (first, last);
        Err(AutopilotError::Unsupported("mission reads".into()))
    }

    /// Every parameter of the autopilot, by name.
    ///
    /// # Errors
    /// Unsupported, not connected, or parameters still missing after the retries.
    async fn list_params(&self) -> Result<Vec<(String, f32)>, AutopilotError> {
        Err(AutopilotError::Unsupported("parameters".into()))
    }

    /// Stops the layer's tasks.
    async fn shutdown(&self);

    /// Uploads `fence` to the autopilot (`None` clears it) so the vehicle enforces it itself.
    /// Layers that cannot upload one answer `Unsupported`; the VAS then keeps checking
    /// waypoints against it alone.
    ///
    /// # Errors
    /// Unsupported, not connected, or the autopilot refused.
    async fn upload_fence(&self, fence: Option<&usal_types::Fence>) -> Result<(), AutopilotError> {
        let _ = fence;
        Err(AutopilotError::Unsupported(
            "this autopilot layer uploads no fence".into(),
        ))
    }
}
