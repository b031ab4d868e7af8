//! The USAL message types the flight services exchange: telemetry, flight states, waypoints,
//! alarms, manual control and state-change requests.
//!
//! These are the payloads of the VAS's middleware items (see `services/vas/README.md` for the
//! item names) and of the FPMa and the ground stations that talk to it. They are plain serde
//! structs with no behaviour beyond naming, so any service can depend on this crate without
//! pulling in another service. [`items`] pairs each of those items' names with its type, as
//! `marea`'s typed handles, for the services that publish, follow or call them.
//!
//! Units: degrees for angles and geographic coordinates, metres, metres per second, seconds.
//!
//! ```
//! use usal_types::{FlightState, VehicleKind};
//! let s: FlightState = "WAYPOINT_NAVIGATION".parse().unwrap();
//! assert_eq!(s, FlightState::WaypointNavigation);
//! assert!(s.applies_to(VehicleKind::Rover));
//! assert!(!FlightState::TakeOff.applies_to(VehicleKind::Rover));
//! ```

#![warn(missing_docs)]

use std::fmt;
use std::str::FromStr;

use serde::{Deserialize, Serialize};

pub mod camera;
pub mod items;
pub mod safety;
pub use safety::{Failsafe, FailsafeKind, Fence, FenceAction, StationHeartbeat};

/// Where the vehicle is. 32 bytes of payload before `alt_rel` (the figure DESIGN §8
/// measures), 40 with it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Position {
    /// Latitude, degrees (WGS-84).
    pub lat: f64,
    /// Longitude, degrees (WGS-84).
    pub lon: f64,
    /// Altitude above mean sea level, metres.
    pub alt: f64,
    /// Heading over ground, degrees from north, 0..360.
    pub heading: f32,
    /// Ground speed, m/s.
    pub speed: f32,
    /// Altitude above the home point, metres (the autopilot's relative altitude).
    #[serde(default)]
    pub alt_rel: f64,
}

/// The autopilot's home (variable `home` of the VAS): where it returns to and what relative
/// altitudes are measured from, as its HOME_POSITION says (set again at arming).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Home {
    /// Latitude, degrees (WGS-84).
    pub lat: f64,
    /// Longitude, degrees (WGS-84).
    pub lon: f64,
    /// Altitude above mean sea level, metres.
    pub alt: f64,
}

/// A point of interest an on-board detector reported (event `detection` of the VAS; the Broz
/// search, seed 002): where it is, how sure the detector is, and which vehicle saw it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PoiDetection {
    /// The detector's number for it.
    pub id: u32,
    /// Latitude, degrees.
    pub lat: f64,
    /// Longitude, degrees.
    pub lon: f64,
    /// How sure the detector is, 0..1.
    pub confidence: f32,
    /// The vehicle that saw it (its namespace, `rover1`); empty as read from MAVLink.
    pub by: String,
}

impl PoiDetection {
    /// The text a detector sends over MAVLink (a STATUSTEXT, at most 50 characters):
    /// `POI <id> <lat> <lon> <confidence>`, 7 decimals (about 1 cm) and 2.
    pub fn to_text(&self) -> String {
        format!(
            "POI {} {:.7} {:.7} {:.2}",
            self.id, self.lat, self.lon, self.confidence
        )
    }

    /// Reads [`PoiDetection::to_text`] back (`by` empty); a text without the confidence (an
    /// older detector) reads as sure. `None` for any other text, coordinates out of range or a
    /// confidence outside 0..1.
    pub fn parse(text: &str) -> Option<Self> {
        let mut it = text.trim().strip_prefix("POI ")?.split_whitespace();
        let id = it.next()?.parse().ok()?;
        let lat: f64 = it.next()?.parse().ok()?;
        let lon: f64 = it.next()?.parse().ok()?;
        let confidence: f32 = match it.next() {
            Some(c) => c.parse().ok()?,
            None => 1.0,
        };
        let ok = (-90.0..=90.0).contains(&lat)
            && (-180.0..=180.0).contains(&lon)
            && (0.0..=1.0).contains(&confidence)
            && it.next().is_none();
        ok.then(|| Self {
            id,
            lat,
            lon,
            confidence,
            by: String::new(),
        })
    }
}

/// What a waypoint's altitude is measured from (a plan's `altRef`), which decides the
/// MAVLink frame of its mission item.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AltRef {
    /// Above mean sea level (MAV_FRAME_GLOBAL_INT).
    Msl,
    /// Above the home point (MAV_FRAME_GLOBAL_RELATIVE_ALT_INT).
    #[default]
    Relative,
    /// Above the terrain below the vehicle (MAV_FRAME_GLOBAL_TERRAIN_ALT_INT), where the
    /// autopilot has terrain data.
    Terrain,
}

impl fmt::Display for AltRef {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Msl => "MSL",
            Self::Relative => "REL",
            Self::Terrain => "AGL",
        })
    }
}

impl FromStr for AltRef {
    type Err = UnknownName;
    /// Accepts a plan's `altRef` values in any case: `MSL`/`AMSL`; `REL`/`RELATIVE`/`HOME`;
    /// `AGL`/`TERRAIN`.
    fn from_str(s: &str) -> Result<Self, UnknownName> {
        match s.trim().to_ascii_uppercase().as_str() {
            "MSL" | "AMSL" => Ok(Self::Msl),
            "REL" | "RELATIVE" | "HOME" => Ok(Self::Relative),
            "AGL" | "TERRAIN" => Ok(Self::Terrain),
            _ => Err(UnknownName {
                what: "altitude reference",
                name: s.to_owned(),
            }),
        }
    }
}

/// Battery state (variable `battery`), from the autopilot's SYS_STATUS or BATTERY_STATUS.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Battery {
    /// Voltage, volts.
    pub voltage: f32,
    /// Current drawn, amps (`None` when the autopilot does not measure it).
    pub current: Option<f32>,
    /// Charge remaining, percent 0..100 (`None` when the autopilot does not estimate it).
    pub remaining: Option<f32>,
}

/// Body attitude, degrees (roll right, pitch up and yaw from north positive).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Attitude {
    /// Roll, degrees.
    pub roll: f32,
    /// Pitch, degrees.
    pub pitch: f32,
    /// Yaw, degrees.
    pub yaw: f32,
}

/// Speeds, m/s.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Speeds {
    /// Speed over ground.
    pub ground: f32,
    /// Airspeed (a rover reports its ground speed here too).
    pub air: f32,
    /// Climb rate, positive up.
    pub climb: f32,
}

/// The kind of vehicle, which decides the flight states and transitions available.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum VehicleKind {
    /// A ground vehicle (APM:Rover in 003).
    #[default]
    Rover,
    /// A multicopter.
    Copter,
    /// A fixed-wing aircraft.
    Plane,
}

impl fmt::Display for VehicleKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Rover => "rover",
            Self::Copter => "copter",
            Self::Plane => "plane",
        })
    }
}

impl FromStr for VehicleKind {
    type Err = UnknownName;
    fn from_str(s: &str) -> Result<Self, UnknownName> {
        match s.to_ascii_lowercase().as_str() {
            "rover" => Ok(Self::Rover),
            "copter" => Ok(Self::Copter),
            "plane" => Ok(Self::Plane),
            _ => Err(UnknownName {
                what: "vehicle kind",
                name: s.to_owned(),
            }),
        }
    }
}

/// A name that does not denote any value of its type.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct UnknownName {
    /// What was being parsed.
    pub what: &'static str,
    /// The offending text.
    pub name: String,
}

impl fmt::Display for UnknownName {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "unknown {} {:?}", self.what, self.name)
    }
}

impl std::error::Error for UnknownName {}

/// The VAS flight states (003 §3.1, §3.3.1). The rover uses the first six and
/// return-to-launch; aircraft add take-off and landing. Serialised as the seed's upper-case
/// names.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum FlightState {
    /// Connecting to and configuring the autopilot (ArduPilot "calibrating"/initialising).
    ConfigureCheck,
    /// Stopped and safe (rover HOLD; aircraft on the ground, disarmed).
    Parking,
    /// The RC pilot drives, no command from the ground (ArduPilot MANUAL for a rover).
    Directed,
    /// The ground station's joystick drives through RC override.
    ManualNavigation,
    /// Autonomous navigation through the waypoint queue (ArduPilot AUTO).
    WaypointNavigation,
    /// Failsafe: the RC transmitter has full control; no way back to navigation.
    Manual,
    /// Aircraft: climbing to the take-off altitude.
    TakeOff,
    /// Aircraft: landing.
    Landing,
    /// Returning to the launch point (every vehicle kind; a rover then holds there).
    ReturnToLaunch,
    /// A plane on the ground, armed, steered by the ground station's joystick at taxiing
    /// speed (throttle capped), to or from its runway; never airborne.
    Taxi,
}

impl FlightState {
    /// Every state, in declaration order.
    pub const ALL: [FlightState; 10] = [
        Self::ConfigureCheck,
        Self::Parking,
        Self::Directed,
        Self::ManualNavigation,
        Self::WaypointNavigation,
        Self::Manual,
        Self::TakeOff,
        Self::Landing,
        Self::ReturnToLaunch,
        Self::Taxi,
    ];

    /// The seed's name, e.g. `WAYPOINT_NAVIGATION`.
    pub fn name(self) -> &'static str {
        match self {
            Self::ConfigureCheck => "CONFIGURE_CHECK",
            Self::Parking => "PARKING",
            Self::Directed => "DIRECTED",
            Self::ManualNavigation => "MANUAL_NAVIGATION",
            Self::WaypointNavigation => "WAYPOINT_NAVIGATION",
            Self::Manual => "MANUAL",
            Self::TakeOff => "TAKE_OFF",
            Self::Landing => "LANDING",
            Self::ReturnToLaunch => "RETURN_TO_LAUNCH",
            Self::Taxi => "TAXI",
        }
    }

    /// Whether a vehicle of `kind` has this state at all.
    pub fn applies_to(self, kind: VehicleKind) -> bool {
        match self {
            Self::TakeOff | Self::Landing => kind != VehicleKind::Rover,
            Self::Taxi => kind == VehicleKind::Plane,
            _ => true,
        }
    }
}

impl fmt::Display for FlightState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FromStr for FlightState {
    type Err = UnknownName;
    /// Accepts the seed's names in any case, with `_`, `-` or spaces.
    fn from_str(s: &str) -> Result<Self, UnknownName> {
        let norm: String = s
            .trim()
            .chars()
            .map(|c| match c {
                '-' | ' ' => '_',
                c => c.to_ascii_uppercase(),
            })
            .collect();
        Self::ALL
            .into_iter()
            .find(|st| st.name() == norm)
            .ok_or_else(|| UnknownName {
                what: "flight state",
                name: s.to_owned(),
            })
    }
}

/// What the autopilot says about itself (from its heartbeat).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct AutopilotStatus {
    /// Heartbeats are arriving.
    pub connected: bool,
    /// Motors armed.
    pub armed: bool,
    /// Autopilot mode name (e.g. ArduPilot `AUTO`), empty when unknown.
    pub mode: String,
    /// Autopilot mode number (ArduPilot custom mode).
    pub mode_number: u32,
    /// Autopilot system state (MAV_STATE without its prefix, e.g. `ACTIVE`).
    pub system_status: String,
}

/// What a waypoint is for.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WaypointKind {
    /// Plain navigation.
    #[default]
    Nav,
    /// Take-off to `alt`.
    Takeoff,
    /// Land at the point.
    Land,
}

/// One waypoint of the stream the FPMa feeds the VAS with.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Waypoint {
    /// The FPMa's sequence number, unique and increasing within a plan; reported back in
    /// [`WaypointReached`].
    pub seq: u64,
    /// Latitude, degrees.
    pub lat: f64,
    /// Longitude, degrees.
    pub lon: f64,
    /// Altitude, metres, measured from `alt_ref`.
    pub alt: f64,
    /// Speed towards this waypoint, m/s (0: the autopilot's cruise speed).
    pub speed: f64,
    /// Pass over the point rather than turning before it.
    pub fly_over: bool,
    /// The flight-plan leg it belongs to.
    pub leg: String,
    /// Navigation, take-off or landing.
    #[serde(default)]
    pub kind: WaypointKind,
    /// What `alt` is measured from (default: the home point).
    #[serde(default)]
    pub alt_ref: AltRef,
    /// The plan's landing sequence begins here: on the autopilot a DO_LAND_START precedes it,
    /// where ArduPilot's RTL_AUTOLAND and MAV_CMD_DO_LAND_START jump to.
    #[serde(default)]
    pub land_start: bool,
}

/// A waypoint of the queue was reached (event `waypoint_reached`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct WaypointReached {
    /// The waypoint's [`Waypoint::seq`].
    pub seq: u64,
    /// Its leg.
    pub leg: String,
    /// Its latitude, degrees.
    pub lat: f64,
    /// Its longitude, degrees.
    pub lon: f64,
    /// Waypoints still queued after it (on the autopilot or waiting).
    pub remaining: u64,
}

/// Answer of `push_waypoints` and `clear_waypoints`: the queue after the call.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct QueueStatus {
    /// Waypoints queued, including the one being navigated to.
    pub queued: u64,
    /// The waypoint being navigated to, if any.
    pub target: Option<u64>,
    /// The last waypoint reached, if any.
    pub last_reached: Option<u64>,
    /// `clear_waypoints` was called and no waypoint has been pushed since: the next push
    /// replaces everything after the current target.
    pub replacing: bool,
    /// Times the autopilot's current item went back to a waypoint already passed while
    /// navigating (0 on a healthy run).
    #[serde(default)]
    pub backtracks: u64,
}

/// Another ground station changed the autopilot's mission (event `mission_changed` of the VAS):
/// the VAS stopped feeding its queue and follows what the autopilot now holds.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MissionChanged {
    /// Who changed it, e.g. `"MAVLink system 250 component 190"`.
    pub by: String,
    /// The mission now on board (item 0 first; `seq` is the item index), as far as it could be
    /// read back; empty when it could not.
    pub waypoints: Vec<Waypoint>,
}

/// Alarm severity, as MAVLink's (and syslog's) levels.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Severity {
    /// The system is unusable.
    Emergency,
    /// Action must be taken at once.
    Alert,
    /// Critical condition.
    Critical,
    /// Error condition.
    Error,
    /// Warning condition.
    Warning,
    /// Normal but significant.
    Notice,
    /// Informational.
    Info,
    /// Debug.
    Debug,
}

/// An alarm (event `alarm`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Alarm {
    /// How bad.
    pub severity: Severity,
    /// What happened, for a human.
    pub text: String,
}

/// A command a service received, who sent it and what it answered (event `commands` of the
/// VAS and the FPMa, recorded in the flight log and the VAS's air-side log).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CommandRecord {
    /// Who sent it: the calling node's `namespace/node` as the access rules see it.
    pub from: String,
    /// The function, e.g. `change_state`.
    pub command: String,
    /// Its arguments, as text (JSON-like debug form).
    pub args: String,
    /// Whether it was obeyed.
    pub ok: bool,
    /// The answer, or why it was refused.
    pub answer: String,
}

impl CommandRecord {
    /// The record of `command` with `args` sent by `from`, answered `result`.
    pub fn of<A: std::fmt::Debug, R: std::fmt::Debug>(
        from: impl std::fmt::Display,
        command: &str,
        args: &A,
        result: &Result<R, String>,
    ) -> Self {
        let (ok, answer) = match result {
            Ok(r) => (true, format!("{r:?}")),
            Err(e) => (false, e.clone()),
        };
        CommandRecord {
            from: from.to_string(),
            command: command.to_owned(),
            args: format!("{args:?}"),
            ok,
            answer,
        }
    }
}

/// Joystick values from the Flight Monitor, as the autopilot layer applies them; they travel
/// addressed to one vehicle inside a [`ManualCommand`].
///
/// Axes are in -1..1 (throttle too: -1 full reverse for a rover, 0 idle), 0 centred.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ManualControl {
    /// Roll (aircraft) or steering (rover), right positive.
    pub roll: f32,
    /// Pitch, nose up positive.
    pub pitch: f32,
    /// Throttle.
    pub throttle: f32,
    /// Yaw, right positive.
    pub yaw: f32,
    /// Sender's time, ms since the Unix epoch; only orders samples, staleness is judged
    /// on arrival so the two clocks need not agree.
    pub timestamp_ms: u64,
}

/// Manual control for one vehicle (the FMo's variable `manual_control`): newest wins.
///
/// One station follows a whole fleet but drives one vehicle at a time, so every sample names
/// the VAS that must obey it and every other VAS ignores it. A VAS that stops receiving
/// samples addressed to it releases its sticks (its `manualTimeoutMs`), so switching the
/// commanded vehicle never leaves the previous one driving.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ManualCommand {
    /// The VAS that obeys, by its item prefix: `namespace/vas` (e.g. `rover1/vas`), or `vas`
    /// for a node without namespace. Exact match: no wildcards, no broadcast.
    pub target: String,
    /// The sticks.
    pub sticks: ManualControl,
}

impl ManualCommand {
    /// Whether the VAS whose items are prefixed `vas_prefix` must obey this sample.
    pub fn is_for(&self, vas_prefix: &str) -> bool {
        self.target == vas_prefix
    }
}

/// Argument of the `change_state` function.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct StateChangeRequest {
    /// The state wanted.
    pub to: FlightState,
}

/// Result of an accepted `change_state` call (a refusal is the call's error, with the reason).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct StateChangeReply {
    /// The state left.
    pub from: FlightState,
    /// The state now.
    pub to: FlightState,
}

/// A command that is not a flight-state change (argument of the VAS function `command`),
/// checked like one by the VAL's command checker (seed 000: Arm, Disarm, ...).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "SCREAMING_SNAKE_CASE")]
pub enum VehicleCommand {
    /// Arm the motors (on the ground, parked).
    Arm,
    /// Disarm the motors (on the ground, parked).
    Disarm,
    /// Aircraft: fly on a bearing at an altitude and speed (DIRECTED, 003 §3.3.1), entering
    /// DIRECTED first when the vehicle is elsewhere.
    Directed(DirectedTarget),
}

impl VehicleCommand {
    /// The command's name, e.g. `ARM`.
    pub fn name(&self) -> &'static str {
        match self {
            Self::Arm => "ARM",
            Self::Disarm => "DISARM",
            Self::Directed(_) => "DIRECTED",
        }
    }
}

impl fmt::Display for VehicleCommand {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

/// What a DIRECTED aircraft flies (003 §3.3.1: "desired altitude, speed and bearing").
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct DirectedTarget {
    /// Altitude above the home point, metres.
    pub alt: f64,
    /// Speed, m/s (ground speed for a copter, airspeed for a plane).
    pub speed: f32,
    /// Bearing, degrees from north, 0..360.
    pub bearing: f32,
}

/// Answer of the VAS function `command`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CommandReply {
    /// The command done.
    pub command: String,
    /// The flight state after it.
    pub state: FlightState,
}

/// What the vehicle may be asked now (VAS variable `allowed_changes`, published with every
/// state change and arming change): the VAL's transition table and command checker answered
/// for the present state, so stations offer exactly these and copy no table.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct AllowedChanges {
    /// The present state (`None` before the VAS knows it).
    pub from: Option<FlightState>,
    /// The vehicle kind.
    pub kind: VehicleKind,
    /// The states `change_state` accepts from here (subject to run-time conditions such as
    /// queued waypoints for WAYPOINT_NAVIGATION).
    pub states: Vec<FlightState>,
    /// The commands `command` accepts from here, by name (`ARM`, `DISARM`, `DIRECTED`).
    pub commands: Vec<String>,
    /// The motors are armed.
    pub armed: bool,
}

/// A flight-state change (event `state_changed`).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct StateChanged {
    /// The state left.
    pub from: FlightState,
    /// The state now.
    pub to: FlightState,
    /// Why: `request` (a `change_state` call), or what the VAS saw (`autopilot mode HOLD`,
    /// `mission complete`, `link lost`...).
    pub cause: String,
}

/// Time since the mission started (variable `mission_time`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MissionTime {
    /// Seconds since the VAS first left PARKING for a navigation state (0 before).
    pub elapsed: f64,
    /// Seconds in the current flight state.
    pub in_state: f64,
}

/// One autopilot parameter, by name (the VAS's `get_param`, `set_param`, `list_params`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ParamValue {
    /// Its name, as the autopilot knows it (`WP_SPEED`), at most 16 characters.
    pub name: String,
    /// Its value (MAVLink carries every parameter as a float).
    pub value: f32,
}

/// A flight log being played back (`usal replay`, variable `replay/status`, twice a second):
/// the stations show REPLAY while it is fresh, so a recorded flight is never taken for a live
/// one, nor a replay's end for a lost link.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ReplayStatus {
    /// The log file played.
    pub log: String,
    /// The mission it recorded.
    pub mission: String,
    /// When it was flown (UTC, as the log's header says).
    pub flown_utc: String,
    /// Seconds into the recorded flight.
    pub at_s: f64,
    /// The recorded flight's length, seconds.
    pub duration_s: f64,
    /// Playback speed (2: twice as fast as flown).
    pub speed: f64,
    /// The playback has ended.
    pub ended: bool,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_detection_fits_a_statustext_and_reads_back() {
        let d = PoiDetection {
            id: 4_000_000_000,
            lat: -89.123_456_7,
            lon: -179.123_456_7,
            confidence: 0.73,
            by: String::new(),
        };
        let t = d.to_text();
        assert!(t.len() <= 50, "{t}");
        let back = PoiDetection::parse(&t).unwrap();
        assert_eq!((back.id, back.confidence), (d.id, 0.73));
        assert!((back.lat - d.lat).abs() < 1e-7 && (back.lon - d.lon).abs() < 1e-7);
        assert_eq!(
            PoiDetection::parse("POI 3 41.2 1.9").unwrap().confidence,
            1.0
        );
        for not in [
            "Reached waypoint #3",
            "POI x 1 2",
            "POI 3 91 1",
            "POI 3 1 1 1.5",
            "xPOI 3 1 1",
        ] {
            assert_eq!(PoiDetection::parse(not), None, "{not}");
        }
    }

    #[test]
    fn state_names_round_trip() {
        for s in FlightState::ALL {
            assert_eq!(s.name().parse::<FlightState>(), Ok(s));
            let json = serde_json::to_string(&s).unwrap();
            assert_eq!(json, format!("\"{}\"", s.name()));
        }
        assert_eq!(
            "manual navigation".parse::<FlightState>(),
            Ok(FlightState::ManualNavigation)
        );
        assert!("FLYING".parse::<FlightState>().is_err());
    }

    #[test]
    fn rover_has_no_aircraft_states() {
        let rover: Vec<_> = FlightState::ALL
            .into_iter()
            .filter(|s| s.applies_to(VehicleKind::Rover))
            .collect();
        assert_eq!(rover.len(), 7);
        assert!(rover.contains(&FlightState::ReturnToLaunch));
        assert!(FlightState::Landing.applies_to(VehicleKind::Copter));
    }

    #[test]
    fn manual_command_is_for_one_vehicle_only() {
        let c = ManualCommand {
            target: "rover1/vas".into(),
            sticks: ManualControl::default(),
        };
        assert!(c.is_for("rover1/vas"));
        for other in [
            "rover2/vas",
            "vas",
            "",
            "rover1",
            "fleet/rover1/vas",
            "*/vas",
        ] {
            assert!(!c.is_for(other), "{other}");
        }
    }

    #[test]
    fn waypoint_kind_defaults_to_nav() {
        let w: Waypoint = serde_json::from_str(
            r#"{"seq":3,"lat":1.0,"lon":2.0,"alt":0.0,"speed":0.0,"fly_over":false,"leg":"a"}"#,
        )
        .unwrap();
        assert_eq!(w.kind, WaypointKind::Nav);
        assert_eq!(w.alt_ref, AltRef::Relative);
        for (text, r) in [
            ("MSL", AltRef::Msl),
            ("rel", AltRef::Relative),
            ("AGL", AltRef::Terrain),
        ] {
            assert_eq!(text.parse::<AltRef>(), Ok(r));
            assert_eq!(r.to_string().parse::<AltRef>(), Ok(r));
        }
        assert!("QNH".parse::<AltRef>().is_err());
        assert_eq!("COPTER".parse::<VehicleKind>(), Ok(VehicleKind::Copter));
    }
}
