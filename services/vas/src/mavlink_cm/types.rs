//! Public data types of the communication manager: events, telemetry, mission items, errors.

use std::time::Duration;

use mavlink::dialects::ardupilotmega::{
    MavCmd, MavFrame, MavMissionResult, MavResult, MavSeverity, MavState, MavType,
    MISSION_ITEM_DATA, MISSION_ITEM_INT_DATA,
};

pub use super::reach::ReachSource;

/// Position from GLOBAL_POSITION_INT, in SI units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Position {
    /// Latitude, degrees.
    pub lat_deg: f64,
    /// Longitude, degrees.
    pub lon_deg: f64,
    /// Altitude above mean sea level, metres.
    pub alt_msl_m: f32,
    /// Altitude above home, metres.
    pub alt_rel_m: f32,
    /// Velocity north, east, down, m/s.
    pub vel_ned: [f32; 3],
    /// Heading, degrees, when known.
    pub heading_deg: Option<f32>,
    /// Autopilot time since boot, ms.
    pub time_boot_ms: u32,
}

/// Attitude from ATTITUDE, radians and rad/s.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Attitude {
    /// Roll, rad.
    pub roll: f32,
    /// Pitch, rad.
    pub pitch: f32,
    /// Yaw, rad.
    pub yaw: f32,
    /// Body rates, rad/s.
    pub rates: [f32; 3],
}

/// VFR_HUD.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VfrHud {
    /// Airspeed, m/s.
    pub airspeed: f32,
    /// Ground speed, m/s.
    pub groundspeed: f32,
    /// Altitude MSL, m.
    pub alt_m: f32,
    /// Climb rate, m/s.
    pub climb: f32,
    /// Heading, degrees.
    pub heading_deg: i16,
    /// Throttle, percent.
    pub throttle_pct: u16,
}

/// SYS_STATUS, the parts a VAS cares about.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SysStatus {
    /// Battery voltage, volts.
    pub voltage_v: f32,
    /// Battery current, amps (`None` when not measured).
    pub current_a: Option<f32>,
    /// Remaining battery, percent (`None` when not estimated).
    pub battery_pct: Option<u8>,
    /// Main loop load, percent.
    pub load_pct: f32,
    /// Sensors present but unhealthy (MAV_SYS_STATUS_SENSOR bits).
    pub unhealthy_sensors: u32,
}

/// BATTERY_STATUS, the parts a VAS publishes.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BatteryStatus {
    /// Which battery (0 the first).
    pub id: u8,
    /// Voltage, volts: the sum of the cells reported (`None` when no cell is).
    pub voltage_v: Option<f32>,
    /// Current, amps (`None` when not measured).
    pub current_a: Option<f32>,
    /// Remaining, percent (`None` when not estimated).
    pub battery_pct: Option<u8>,
}

/// What the manager reports, in arrival order, on [`super::MavlinkManager::subscribe`].
#[derive(Clone, Debug, PartialEq)]
pub enum MavEvent {
    /// First heartbeat from the autopilot on this manager.
    Connected {
        /// Autopilot system id.
        system_id: u8,
        /// Autopilot component id.
        component_id: u8,
        /// Vehicle type.
        vehicle_type: MavType,
    },
    /// Every autopilot HEARTBEAT.
    Heartbeat {
        /// Custom (ArduPilot) mode number.
        mode: u32,
        /// ArduPilot name of the mode, when known.
        mode_name: Option<&'static str>,
        /// Armed flag.
        armed: bool,
        /// MAV_STATE.
        system_status: MavState,
    },
    /// The mode differs from the previous heartbeat's (changed by us, the RC or the autopilot).
    ModeChanged {
        /// Previous mode, `None` on the first heartbeat.
        from: Option<u32>,
        /// New mode.
        to: u32,
        /// ArduPilot name of the new mode.
        name: Option<&'static str>,
    },
    /// Armed state differs from the previous heartbeat's.
    ArmedChanged {
        /// New state.
        armed: bool,
    },
    /// STATUSTEXT.
    StatusText {
        /// Severity.
        severity: MavSeverity,
        /// Text.
        text: String,
    },
    /// GLOBAL_POSITION_INT.
    Position(Position),
    /// HOME_POSITION: the autopilot's home (set at arming, asked for with
    /// [`super::MavlinkManager::request_home`]).
    Home(usal_types::Home),
    /// ATTITUDE.
    Attitude(Attitude),
    /// VFR_HUD.
    VfrHud(VfrHud),
    /// SYS_STATUS.
    SysStatus(SysStatus),
    /// BATTERY_STATUS.
    BatteryStatus(BatteryStatus),
    /// MISSION_CURRENT changed.
    MissionCurrent {
        /// New current index.
        seq: u16,
    },
    /// A mission item was reached, reported once per visit whatever the source.
    WaypointReached {
        /// Index of the item.
        seq: u16,
        /// The message that revealed it.
        source: ReachSource,
    },
    /// The autopilot accepted a mission write (upload, partial write, clear) from another
    /// ground station: what it holds is no longer what we uploaded.
    MissionChangedElsewhere {
        /// That station's system id.
        system_id: u8,
        /// Its component id.
        component_id: u8,
    },
    /// No heartbeat for the configured timeout (or the transport failed).
    LinkLost,
    /// Heartbeats again after a loss.
    LinkRestored,
}

/// A mission item, independent of the MISSION_ITEM / MISSION_ITEM_INT encoding.
///
/// `x`/`y` are latitude/longitude in degrees × 10⁷ for global frames (as in
/// MISSION_ITEM_INT), `z` the altitude in metres in `frame`.
#[derive(Clone, Debug, PartialEq)]
pub struct MissionItem {
    /// MAV_CMD.
    pub command: MavCmd,
    /// Coordinate frame.
    pub frame: MavFrame,
    /// param1..param4.
    pub params: [f32; 4],
    /// Latitude × 10⁷ (or local x × 10⁴).
    pub x: i32,
    /// Longitude × 10⁷ (or local y × 10⁴).
    pub y: i32,
    /// Altitude, metres.
    pub z: f32,
    /// Continue to the next item when done.
    pub autocontinue: bool,
}

fn is_global(frame: MavFrame) -> bool {
    !matches!(
        frame,
        MavFrame::MAV_FRAME_LOCAL_NED
            | MavFrame::MAV_FRAME_LOCAL_ENU
            | MavFrame::MAV_FRAME_LOCAL_OFFSET_NED
            | MavFrame::MAV_FRAME_MISSION
    )
}

impl MissionItem {
    /// A NAV_WAYPOINT at `lat`, `lon` (degrees), `alt_m` above home.
    pub fn waypoint(lat_deg: f64, lon_deg: f64, alt_m: f32) -> Self {
        Self {
            command: MavCmd::MAV_CMD_NAV_WAYPOINT,
            frame: MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT,
            params: [0.0; 4],
            x: (lat_deg * 1e7).round() as i32,
            y: (lon_deg * 1e7).round() as i32,
            z: alt_m,
            autocontinue: true,
        }
    }

    /// Latitude, degrees.
    pub fn lat_deg(&self) -> f64 {
        f64::from(self.x) / 1e7
    }

    /// Longitude, degrees.
    pub fn lon_deg(&self) -> f64 {
        f64::from(self.y) / 1e7
    }

    pub(crate) fn to_int(&self, seq: u16, target: (u8, u8)) -> MISSION_ITEM_INT_DATA {
        MISSION_ITEM_INT_DATA {
            param1: self.params[0],
            param2: self.params[1],
            param3: self.params[2],
            param4: self.params[3],
            x: self.x,
            y: self.y,
            z: self.z,
            seq,
            command: self.command,
            target_system: target.0,
            target_component: target.1,
            frame: self.frame,
            current: 0,
            autocontinue: u8::from(self.autocontinue),
            ..Default::default()
        }
    }

    pub(crate) fn to_float(&self, seq: u16, target: (u8, u8)) -> MISSION_ITEM_DATA {
        let scale = if is_global(self.frame) { 1e7 } else { 1e4 };
        MISSION_ITEM_DATA {
            param1: self.params[0],
            param2: self.params[1],
            param3: self.params[2],
            param4: self.params[3],
            x: (f64::from(self.x) / scale) as f32,
            y: (f64::from(self.y) / scale) as f32,
            z: self.z,
            seq,
            command: self.command,
            target_system: target.0,
            target_component: target.1,
            frame: self.frame,
            current: 0,
            autocontinue: u8::from(self.autocontinue),
            ..Default::default()
        }
    }

    pub(crate) fn from_int(m: &MISSION_ITEM_INT_DATA) -> Self {
        Self {
            command: m.command,
            frame: m.frame,
            params: [m.param1, m.param2, m.param3, m.param4],
            x: m.x,
            y: m.y,
            z: m.z,
            autocontinue: m.autocontinue != 0,
        }
    }

    pub(crate) fn from_float(m: &MISSION_ITEM_DATA) -> Self {
        let scale = if is_global(m.frame) { 1e7 } else { 1e4 };
        Self {
            command: m.command,
            frame: m.frame,
            params: [m.param1, m.param2, m.param3, m.param4],
            x: (f64::from(m.x) * scale).round() as i32,
            y: (f64::from(m.y) * scale).round() as i32,
            z: m.z,
            autocontinue: m.autocontinue != 0,
        }
    }
}

/// Errors opening the manager.
#[derive(Debug, thiserror::Error)]
pub enum ManagerOpenError {
    /// The endpoint string is malformed.
    #[error(transparent)]
    Endpoint(#[from] mavconn::EndpointParseError),
}

/// Errors shared by every request to the autopilot.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LinkError {
    /// No autopilot heartbeat has been seen (within the wait).
    #[error("no autopilot heartbeat within {0:?}")]
    NotConnected(Duration),
    /// The manager was shut down.
    #[error("the MAVLink manager is shut down")]
    Closed,
}

/// Errors of COMMAND_LONG-based operations (mode, arming, rates).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CommandError {
    /// See [`LinkError`].
    #[error(transparent)]
    Link(#[from] LinkError),
    /// No COMMAND_ACK after all retries.
    #[error("no COMMAND_ACK for {command:?} after {attempts} attempts")]
    RetriesExhausted {
        /// The command.
        command: MavCmd,
        /// Attempts made.
        attempts: u32,
    },
    /// The autopilot answered with something other than ACCEPTED.
    #[error("{command:?} refused: {result:?}")]
    Rejected {
        /// The command.
        command: MavCmd,
        /// The autopilot's answer.
        result: MavResult,
    },
    /// The mode name is not an ArduPilot mode of this vehicle type.
    #[error("unknown mode {0:?} for this vehicle")]
    UnknownMode(String),
    /// Accepted, but the heartbeat never showed the new state.
    #[error("accepted but not confirmed by the heartbeat: {0}")]
    NotConfirmed(String),
}

/// Errors of the parameter protocol.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ParamError {
    /// See [`LinkError`].
    #[error(transparent)]
    Link(#[from] LinkError),
    /// Names are at most 16 characters.
    #[error("parameter name {0:?} is longer than 16 characters")]
    NameTooLong(String),
    /// No PARAM_VALUE after all retries (unknown names are silently ignored by ArduPilot).
    #[error("no PARAM_VALUE for {name} after {attempts} attempts")]
    RetriesExhausted {
        /// Parameter name (or `#index`).
        name: String,
        /// Attempts made.
        attempts: u32,
    },
    /// The autopilot answered with a different value than requested.
    #[error("{name} set to {requested} but the autopilot reports {actual}")]
    NotApplied {
        /// Parameter name.
        name: String,
        /// Value sent.
        requested: f32,
        /// Value reported.
        actual: f32,
    },
}

/// Which step of a mission transaction failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MissionStage {
    /// Waiting for the first request after MISSION_COUNT / MISSION_WRITE_PARTIAL_LIST.
    Start,
    /// Waiting for the request or ACK following item `seq` (upload), or for item `seq` (download).
    Item(u16),
    /// Waiting for the final MISSION_ACK.
    Ack,
    /// Waiting for MISSION_COUNT after MISSION_REQUEST_LIST.
    Count,
    /// Waiting for MISSION_CURRENT after MISSION_SET_CURRENT.
    SetCurrent,
}

/// Errors of the mission protocol.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MissionError {
    /// See [`LinkError`].
    #[error(transparent)]
    Link(#[from] LinkError),
    /// The autopilot stopped answering; the transfer was cancelled.
    #[error("mission transfer gave up at {stage:?} after {attempts} attempts")]
    RetriesExhausted {
        /// Where it stalled.
        stage: MissionStage,
        /// Attempts made at that stage.
        attempts: u32,
    },
    /// The autopilot refused or aborted the transfer.
    #[error("autopilot answered {0:?}")]
    Rejected(MavMissionResult),
    /// The request does not make sense (empty list, range past the end...).
    #[error("invalid mission request: {0}")]
    Invalid(String),
    /// The autopilot does not answer or refuses MISSION_WRITE_PARTIAL_LIST (found out once per
    /// connection by a short probe): upload whole missions instead.
    #[error("the autopilot has no partial mission writes")]
    PartialUnsupported,
}
