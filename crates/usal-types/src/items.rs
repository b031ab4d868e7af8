//! The catalogue of the middleware items whose payloads are this crate's types: each item's
//! name in its service together with its type, as a [`marea`] typed handle. A subscriber, caller
//! or provider names an item through its constant (`vas::POSITION.subscribe(&svc, "rover1/vas")`)
//! instead of writing the name and the type apart at each use; the names on the wire are the
//! strings below. `services/vas/README.md` says what each item carries and when.
//!
//! ```
//! use usal_types::items::vas;
//! assert_eq!(vas::POSITION.at("rover1/vas"), "rover1/vas/position");
//! assert_eq!(vas::CHANGE_STATE.at("**/vas"), "**/vas/change_state");
//! ```

/// The VAS's items (the `vas` service: `<namespace>/vas/<item>`).
pub mod vas {
    use marea::{EventItem, FunctionItem, VariableItem};

    use crate::{
        Alarm, AllowedChanges, Attitude, AutopilotStatus, Battery, CommandRecord, CommandReply,
        Failsafe, Fence, FlightState, Home, MissionChanged, MissionTime, ParamValue, PoiDetection,
        Position, QueueStatus, Speeds, StateChangeReply, StateChangeRequest, StateChanged,
        VehicleCommand, Waypoint, WaypointReached,
    };

    /// Where the vehicle is, at the telemetry rate.
    pub const POSITION: VariableItem<Position> = VariableItem::new("position");
    /// The autopilot's home.
    pub const HOME: VariableItem<Home> = VariableItem::new("home");
    /// The fence in force (an empty fence when none).
    pub const FENCE: VariableItem<Fence> = VariableItem::new("fence");
    /// Roll, pitch and yaw.
    pub const ATTITUDE: VariableItem<Attitude> = VariableItem::new("attitude");
    /// Ground, air and climb speeds.
    pub const SPEEDS: VariableItem<Speeds> = VariableItem::new("speeds");
    /// Voltage, current and charge left.
    pub const BATTERY: VariableItem<Battery> = VariableItem::new("battery");
    /// The autopilot's link, arming and mode.
    pub const AUTOPILOT: VariableItem<AutopilotStatus> = VariableItem::new("autopilot");
    /// The USAL flight state.
    pub const FLIGHT_STATE: VariableItem<FlightState> = VariableItem::new("flight_state");
    /// What may be asked from the present state (states and commands).
    pub const ALLOWED_CHANGES: VariableItem<AllowedChanges> = VariableItem::new("allowed_changes");
    /// Time since the mission started and in the present state.
    pub const MISSION_TIME: VariableItem<MissionTime> = VariableItem::new("mission_time");
    /// The waypoint queue at the autopilot.
    pub const QUEUE: VariableItem<QueueStatus> = VariableItem::new("queue");

    /// A flight state change and its cause.
    pub const STATE_CHANGED: EventItem<StateChanged> = EventItem::new("state_changed");
    /// A waypoint reached, once per waypoint, in order.
    pub const WAYPOINT_REACHED: EventItem<WaypointReached> = EventItem::new("waypoint_reached");
    /// Another ground station's mission write, accepted by the autopilot.
    pub const MISSION_CHANGED: EventItem<MissionChanged> = EventItem::new("mission_changed");
    /// A point of interest an on-board detector reported.
    pub const DETECTION: EventItem<PoiDetection> = EventItem::new("detection");
    /// Something the operator should know.
    pub const ALARM: EventItem<Alarm> = EventItem::new("alarm");
    /// A command received, who sent it and the answer.
    pub const COMMANDS: EventItem<CommandRecord> = EventItem::new("commands");
    /// A failsafe fired (link lost or restored, fence, battery) and what was done.
    pub const FAILSAFE: EventItem<Failsafe> = EventItem::new("failsafe");

    /// Asks for a flight state.
    pub const CHANGE_STATE: FunctionItem<StateChangeRequest, StateChangeReply> =
        FunctionItem::new("change_state");
    /// The states `change_state` accepts now.
    pub const ALLOWED_STATES: FunctionItem<(), Vec<FlightState>> =
        FunctionItem::new("allowed_states");
    /// ARM, DISARM or DIRECTED.
    pub const COMMAND: FunctionItem<VehicleCommand, CommandReply> = FunctionItem::new("command");
    /// Appends waypoints to the queue.
    pub const PUSH_WAYPOINTS: FunctionItem<Vec<Waypoint>, QueueStatus> =
        FunctionItem::new("push_waypoints");
    /// Announces a new queue.
    pub const CLEAR_WAYPOINTS: FunctionItem<(), QueueStatus> = FunctionItem::new("clear_waypoints");
    /// Narrows the vehicle's fence (`None`: back to the vehicle's own); answers what was done.
    pub const SET_FENCE: FunctionItem<Option<Fence>, String> = FunctionItem::new("set_fence");
    /// Reads an autopilot parameter.
    pub const GET_PARAM: FunctionItem<String, ParamValue> = FunctionItem::new("get_param");
    /// Sets an autopilot parameter; answers the value the autopilot took.
    pub const SET_PARAM: FunctionItem<ParamValue, ParamValue> = FunctionItem::new("set_param");
    /// Every parameter the autopilot has.
    pub const LIST_PARAMS: FunctionItem<(), Vec<ParamValue>> = FunctionItem::new("list_params");
    /// Mission items `first..=last` as the autopilot holds them.
    pub const READ_MISSION: FunctionItem<(u16, u16), Vec<Waypoint>> =
        FunctionItem::new("read_mission");
}

/// The Flight Monitor's items (the `fmo` service).
pub mod fmo {
    use marea::VariableItem;

    use crate::ManualCommand;

    /// The sticks, addressed to the one vehicle they command, while the dead-man is held.
    pub const MANUAL_CONTROL: VariableItem<ManualCommand> = VariableItem::new("manual_control");
}

/// What every ground station's service publishes, whatever its name (the FMo's `fmo`, the
/// launcher's `station`).
pub mod station {
    use marea::VariableItem;

    use crate::StationHeartbeat;

    /// The station's liveness, which a VAS watches for its lost-link failsafe.
    pub const HEARTBEAT: VariableItem<StationHeartbeat> = VariableItem::new("heartbeat");
}

/// The items of `usal replay` (its `replay` service).
pub mod replay {
    use marea::VariableItem;

    use crate::ReplayStatus;

    /// Where the replay is, so a station shows a recorded flight as one.
    pub const STATUS: VariableItem<ReplayStatus> = VariableItem::new("status");
}

/// The camera service's items (`<namespace>/camera/<item>`).
pub mod camera {
    use marea::{FunctionItem, VariableItem};

    use crate::camera::CameraFrame;

    /// The latest frame, JPEG: for the stations, over any link but a radio.
    pub const FRAME: VariableItem<CameraFrame> = VariableItem::new("frame");
    /// The latest frame, uncompressed (`rgb8`): for services on board, over shared memory.
    pub const RAW: VariableItem<CameraFrame> = VariableItem::new("raw");
    /// The latest frame as a small JPEG at most this many pixels wide: over a radio, on
    /// request.
    pub const SNAPSHOT: FunctionItem<u32, CameraFrame> = FunctionItem::new("snapshot");
}
