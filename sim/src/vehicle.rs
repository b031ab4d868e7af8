//! The simulated autopilot: MAVLink message handling, modes, arming, mission
//! navigation and telemetry, all pure (time is passed in) so it is unit-testable.
//!
//! Navigation follows what 003 §2.5.4 observed of APM:Rover: the vehicle
//! memorises the item it is driving to; a new upload or partial write does not
//! change it, MISSION_SET_CURRENT does; when it is reached the *next index of
//! the mission now on board* becomes the target; after the last item a rover
//! switches to HOLD.
//!
//! Layout: this file holds the state, navigation and the simulation step; `inbound` handles
//! the messages received, `telemetry` the wall-clock duties and the messages built to send;
//! `fence_tests` tests the geofence through the whole vehicle.
//! It stays over 800 lines because of its tests (about 850 lines), which drive the whole
//! vehicle through `handle`, `step` and `poll` and so belong with the state they inspect.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use mavlink::dialects::ardupilotmega::{
    MavAutopilot, MavCmd, MavDataStream, MavFrame, MavMessage, MavModeFlag, MavProtocolCapability,
    MavResult, MavSeverity, MavState, MavSysStatusSensor, MavType, ATTITUDE_DATA,
    AUTOPILOT_VERSION_DATA, COMMAND_ACK_DATA, COMMAND_LONG_DATA, GLOBAL_POSITION_INT_DATA,
    HEARTBEAT_DATA, HOME_POSITION_DATA, MISSION_CURRENT_DATA, MISSION_ITEM_REACHED_DATA,
    PARAM_VALUE_DATA, STATUSTEXT_DATA, SYS_STATUS_DATA, VFR_HUD_DATA,
};

use crate::battery::{Battery, BatteryConfig};
use crate::fence::{FenceParams, FenceStore};
use crate::kinematics::{Command, GeoPoint, Limits, LocalFrame, Ned, State, VehicleKind};
use crate::log::LogEvent;
use crate::mission::{self, Change, Item, MissionStore};
use crate::modes::{self, Behaviour};
use crate::params::Params;
use crate::profile::Profile;

#[cfg(test)]
mod fence_tests;
mod inbound;
mod telemetry;

/// How long an RC override stays in force without being refreshed (ArduPilot RC_OVERRIDE_TIME).
const RC_OVERRIDE_TIMEOUT: Duration = Duration::from_secs(3);
/// Heartbeat period, wall time, whatever the speed-up.
const HEARTBEAT_PERIOD: Duration = Duration::from_secs(1);

/// Message ids the simulator can stream.
const STREAMABLE: [u32; 5] = [
    SYS_STATUS_ID,
    ATTITUDE_ID,
    GLOBAL_POSITION_INT_ID,
    MISSION_CURRENT_ID,
    VFR_HUD_ID,
];
const SYS_STATUS_ID: u32 = 1;
const ATTITUDE_ID: u32 = 30;
const GLOBAL_POSITION_INT_ID: u32 = 33;
const MISSION_CURRENT_ID: u32 = 42;
const VFR_HUD_ID: u32 = 74;
/// Answered to MAV_CMD_REQUEST_MESSAGE (and REQUEST_AUTOPILOT_CAPABILITIES), never streamed.
const AUTOPILOT_VERSION_ID: u32 = 148;
/// Answered to MAV_CMD_REQUEST_MESSAGE (and MAV_CMD_GET_HOME_POSITION), never streamed.
const HOME_POSITION_ID: u32 = 242;

/// Static configuration of a simulated vehicle.
#[derive(Clone, Copy, Debug)]
pub struct VehicleConfig {
    /// Motion model and mode table.
    pub kind: VehicleKind,
    /// MAVLink system id.
    pub sysid: u8,
    /// Home position (mission item 0, RTL point, start position).
    pub home: GeoPoint,
}

#[derive(Clone, Copy, Debug)]
struct Target {
    seq: u16,
    pos: Ned,
    lat: f64,
    lon: f64,
    /// The item's own acceptance radius (NAV_WAYPOINT param2), else WP_RADIUS.
    radius: Option<f64>,
    /// A NAV_LAND: the vehicle lands at the point instead of passing it.
    land: bool,
    /// Where the vehicle was when the item became current (a plane glides from there).
    from: Ned,
}

#[derive(Clone, Copy, Debug, Default)]
struct Sticks {
    steer: f64,
    throttle: f64,
}

/// The simulated autopilot.
pub struct Vehicle {
    cfg: VehicleConfig,
    frame: LocalFrame,
    state: State,
    mode: u32,
    armed: bool,
    params: Params,
    mission: MissionStore,
    current: u16,
    target: Option<Target>,
    hold_point: Ned,
    /// Where a GUIDED take-off climbs to (MAV_CMD_NAV_TAKEOFF), or a plane's TAKEOFF mode.
    takeoff_to: Option<Ned>,
    /// Where GUIDED flies to (MAV_CMD_DO_REPOSITION) until it holds there.
    guided_to: Option<Ned>,
    /// Where MAV_CMD_DO_REPOSITION sent the vehicle (PX4 profile, in its hold mode): it goes
    /// there, then holds there.
    reposition: Option<(Ned, GeoPoint)>,
    /// Speed set by DO_CHANGE_SPEED (mission item or command) until the mode changes, m/s.
    speed_override: Option<f64>,
    /// Report no progress: no MISSION_ITEM_REACHED, no "Reached" text, MISSION_CURRENT only
    /// in answer to a set-current (autopilots that leave progress to be inferred).
    quiet_progress: bool,
    /// Simulated seconds between a reach and the advance to the next item (0: at once).
    late_advance_s: f64,
    /// A late advance due: at this simulated time, to this item.
    pending_advance: Option<(f64, u16)>,
    /// The steady wind's velocity, metres per second north and east (see
    /// [`Limits::wind`]).
    wind: (f64, f64),
    /// Simulated time before which the autopilot's own checks are not done: mode changes and
    /// arming are answered TEMPORARILY_REJECTED.
    ready_at: f64,
    /// Which autopilot's conventions to follow.
    profile: Profile,
    sticks: Option<(Sticks, Instant)>,
    sim_time: f64,
    /// Drained while armed, by time and distance; reported in SYS_STATUS.
    battery: Battery,
    streams: BTreeMap<u32, (Duration, Instant)>,
    /// The geofence on board.
    fence: FenceStore,
    next_heartbeat: Instant,
    log: Vec<(f64, LogEvent)>,
}

fn kind_name(kind: VehicleKind) -> &'static str {
    match kind {
        VehicleKind::Rover => "rover",
        VehicleKind::Copter => "copter",
        VehicleKind::Plane => "plane",
    }
}

/// Whether a command moves the vehicle (and is therefore "reached"); the others
/// (DO_*, CONDITION_*) are executed instantly when the mission passes them.
/// Height above the ground at which a landing counts as touched down, metres.
const TOUCHDOWN_M: f64 = 0.05;

fn is_nav(cmd: MavCmd) -> bool {
    (cmd as u32) < 80 || matches!(cmd, MavCmd::MAV_CMD_NAV_SPLINE_WAYPOINT)
}

fn statustext(severity: MavSeverity, text: &str) -> MavMessage {
    MavMessage::STATUSTEXT(STATUSTEXT_DATA {
        severity,
        text: text.into(),
        ..Default::default()
    })
}

fn command_ack(command: MavCmd, result: MavResult) -> MavMessage {
    MavMessage::COMMAND_ACK(COMMAND_ACK_DATA {
        command,
        result,
        ..Default::default()
    })
}

/// Maps an RC PWM value to -1..1 around 1500; 0 and 65535 mean "no override".
fn pwm_to_unit(pwm: u16) -> Option<f64> {
    if pwm == 0 || pwm == u16::MAX {
        None
    } else {
        Some(((f64::from(pwm) - 1500.0) / 500.0).clamp(-1.0, 1.0))
    }
}

impl Vehicle {
    /// A disarmed vehicle at home in its initial mode.
    pub fn new(cfg: VehicleConfig, now: Instant) -> Self {
        let params = Params::defaults(cfg.kind, cfg.sysid, Profile::ArduPilot);
        let mut v = Self {
            cfg,
            frame: LocalFrame::new(cfg.home),
            state: State::at(Ned::default()),
            mode: modes::initial(cfg.kind),
            armed: false,
            mission: MissionStore::new(cfg.home),
            current: 0,
            target: None,
            hold_point: Ned::default(),
            takeoff_to: None,
            guided_to: None,
            reposition: None,
            speed_override: None,
            quiet_progress: false,
            late_advance_s: 0.0,
            pending_advance: None,
            ready_at: 0.0,
            wind: (0.0, 0.0),
            profile: Profile::ArduPilot,
            sticks: None,
            sim_time: 0.0,
            battery: Battery::new(BatteryConfig::default()),
            streams: BTreeMap::new(),
            fence: FenceStore::default(),
            next_heartbeat: now,
            log: Vec::new(),
            params,
        };
        let hz = |name| v.params.get_or(name, 1.0);
        let defaults = [
            (GLOBAL_POSITION_INT_ID, hz("SR0_POSITION")),
            (ATTITUDE_ID, hz("SR0_EXTRA1")),
            (VFR_HUD_ID, hz("SR0_EXTRA2")),
            (SYS_STATUS_ID, hz("SR0_EXT_STAT")),
            (MISSION_CURRENT_ID, hz("SR0_EXT_STAT")),
        ];
        for (id, rate) in defaults {
            v.set_rate(id, f64::from(rate), now);
        }
        v.record(LogEvent::Started {
            vehicle: kind_name(cfg.kind).to_owned(),
            sysid: cfg.sysid,
            home_lat: cfg.home.lat_deg,
            home_lon: cfg.home.lon_deg,
        });
        v
    }

    /// A steady wind of `speed` m/s blowing from `from_deg` (degrees clockwise from north).
    pub fn set_wind(&mut self, speed: f64, from_deg: f64) {
        self.wind = crate::kinematics::wind_from(speed, from_deg);
    }

    /// Answers mode changes and arming MAV_RESULT_TEMPORARILY_REJECTED for the first
    /// `seconds` of simulated time, as an autopilot whose pre-flight checks are still running
    /// does (PX4, a MAVSDK-built vehicle): a ground station must ask again.
    pub fn set_not_ready_for(&mut self, seconds: f64) {
        self.ready_at = self.sim_time + seconds.max(0.0);
    }

    /// Whether the autopilot's own checks are still running (see [`Self::set_not_ready_for`]).
    pub(super) fn not_ready(&self) -> bool {
        self.sim_time < self.ready_at
    }

    /// Stops (or resumes) reporting mission progress: no MISSION_ITEM_REACHED, no "Reached"
    /// STATUSTEXT, no MISSION_CURRENT stream or change; set-currents are still answered.
    pub fn set_quiet_progress(&mut self, quiet: bool) {
        self.quiet_progress = quiet;
    }

    /// Moves the current item on `seconds` (simulated) after reporting a waypoint reached,
    /// holding meanwhile, and to the item after the one reached whatever was set since: a
    /// set-current sent before it is overridden, as MAVSDK's mission server does.
    pub fn set_late_advance(&mut self, seconds: f64) {
        self.late_advance_s = seconds.max(0.0);
    }

    /// Follows `profile`'s conventions (heartbeat, modes, item 0, partial writes, current item
    /// after an upload, MISSION_CURRENT, the geofence's parameters); see [`crate::profile`].
    /// The parameter table becomes `profile`'s, keeping the values set of those both share.
    pub fn set_profile(&mut self, profile: Profile) {
        self.profile = profile;
        self.mission.set_item0_is_home(profile.item0_is_home());
        self.params = self.params.rebuilt_for(self.cfg.kind, profile);
    }

    /// The most items one fence transfer may have (`--fence-capacity`; a larger MISSION_COUNT
    /// is answered NO_SPACE).
    pub fn set_fence_capacity(&mut self, capacity: u16) {
        self.fence.set_capacity(capacity);
    }

    /// The autopilot profile followed.
    pub fn profile(&self) -> Profile {
        self.profile
    }

    /// Replaces the battery with a full one of this size.
    pub fn set_battery(&mut self, cfg: BatteryConfig) {
        self.battery = Battery::new(cfg);
    }

    /// The battery.
    pub fn battery(&self) -> &Battery {
        &self.battery
    }

    /// Current custom mode number.
    pub fn mode(&self) -> u32 {
        self.mode
    }

    /// Whether armed.
    pub fn armed(&self) -> bool {
        self.armed
    }

    /// Current mission index (MISSION_CURRENT).
    pub fn current(&self) -> u16 {
        self.current
    }

    /// The item being driven to, if any.
    pub fn target_seq(&self) -> Option<u16> {
        self.target.map(|t| t.seq)
    }

    /// Position in the local frame.
    pub fn position(&self) -> Ned {
        self.state.pos
    }

    /// Heading, degrees from north, clockwise (0..360).
    pub fn heading_deg(&self) -> f64 {
        self.state.yaw.to_degrees().rem_euclid(360.0)
    }

    /// The local frame (home and its axes).
    pub fn frame(&self) -> &LocalFrame {
        &self.frame
    }

    /// Simulated seconds since start.
    pub fn sim_time(&self) -> f64 {
        self.sim_time
    }

    /// The on-board mission.
    pub fn mission(&self) -> &[Item] {
        self.mission.items()
    }

    /// Events since the last call, with their simulated time.
    pub fn take_log(&mut self) -> Vec<(f64, LogEvent)> {
        std::mem::take(&mut self.log)
    }

    fn record(&mut self, event: LogEvent) {
        self.log.push((self.sim_time, event));
    }

    fn limits(&self) -> Limits {
        let p = |name, default| f64::from(self.params.get_or(name, default));
        let speed = |default: f64| self.speed_override.unwrap_or(default).max(0.1);
        match self.cfg.kind {
            VehicleKind::Rover => Limits {
                loiter_radius: 2.0,
                ..Limits::calm(
                    speed(p("CRUISE_SPEED", 2.0)),
                    p("ATC_STR_RAT_MAX", 120.0).max(1.0).to_radians(),
                    p("ATC_ACCEL_MAX", 2.0).max(0.1),
                    0.0,
                )
            },
            VehicleKind::Copter => Limits {
                wind: self.wind,
                ..Limits::calm(
                    speed(p("WPNAV_SPEED", 500.0) / 100.0),
                    p("ATC_RATE_Y_MAX", 90.0).max(1.0).to_radians(),
                    (p("WPNAV_ACCEL", 250.0) / 100.0).max(0.1),
                    (p("WPNAV_SPEED_UP", 250.0) / 100.0).max(0.1),
                )
            },
            VehicleKind::Plane => {
                // Asked to fly slower than it can, a plane flies at its stall margin.
                let stall = p("AIRSPEED_MIN", 9.0).max(1.0);
                let speed = speed(p("AIRSPEED_CRUISE", 15.0)).max(stall);
                let bank = p("ROLL_LIMIT_DEG", 45.0).clamp(5.0, 80.0).to_radians();
                Limits {
                    // Coordinated turn at the bank limit: ω = g·tan(φ)/v, so the turn radius
                    // v²/(g·tan φ) grows with the speed.
                    loiter_radius: p("WP_LOITER_RAD", 60.0).max(10.0),
                    wind: self.wind,
                    stall_speed: stall,
                    ..Limits::calm(
                        speed,
                        9.81 * bank.tan() / speed,
                        3.0,
                        p("TECS_CLMB_MAX", 5.0).max(0.1),
                    )
                }
            }
        }
    }

    fn wp_radius(&self) -> f64 {
        f64::from(self.params.get_or("WP_RADIUS", 2.0)).max(0.1)
    }

    fn behaviour(&self) -> Behaviour {
        modes::lookup(self.cfg.kind, self.mode).map_or(Behaviour::Hold, |m| m.2)
    }

    fn for_us(&self, target_system: u8) -> bool {
        target_system == 0 || target_system == self.cfg.sysid
    }

    // ---------------------------------------------------------------- navigation

    fn target_of(&self, seq: u16) -> Option<Target> {
        let item = self.mission.items().get(usize::from(seq))?;
        let lat = f64::from(item.x) / 1e7;
        let lon = f64::from(item.y) / 1e7;
        let mut pos = if item.x == 0 && item.y == 0 {
            // ArduPilot: a waypoint at 0,0 means "here".
            self.state.pos
        } else {
            self.frame.to_local(GeoPoint {
                lat_deg: lat,
                lon_deg: lon,
                alt_m: 0.0,
            })
        };
        pos.up = match item.frame {
            MavFrame::MAV_FRAME_GLOBAL | MavFrame::MAV_FRAME_GLOBAL_INT => {
                f64::from(item.z) - self.cfg.home.alt_m
            }
            _ => f64::from(item.z),
        };
        if self.cfg.kind == VehicleKind::Rover {
            pos.up = 0.0;
        }
        if item.command == MavCmd::MAV_CMD_NAV_RETURN_TO_LAUNCH {
            pos = Ned::default();
        }
        if item.command == MavCmd::MAV_CMD_NAV_TAKEOFF {
            // ArduCopter climbs straight up where it stands, whatever lat/lon say.
            pos.north = self.state.pos.north;
            pos.east = self.state.pos.east;
        }
        let radius = (item.command == MavCmd::MAV_CMD_NAV_WAYPOINT
            && item.param2.is_finite()
            && item.param2 > 0.0)
            .then(|| f64::from(item.param2));
        Some(Target {
            seq,
            pos,
            lat,
            lon,
            radius,
            land: item.command == MavCmd::MAV_CMD_NAV_LAND,
            from: self.state.pos,
        })
    }

    /// Executes the DO_ item at `seq` the mission passes over.
    fn do_item(&mut self, seq: u16, item: &Item) {
        self.record(LogEvent::DoCommand {
            seq,
            command: item.command as u32,
        });
        if item.command == MavCmd::MAV_CMD_DO_CHANGE_SPEED {
            self.change_speed(item.param2);
        }
    }

    /// DO_CHANGE_SPEED's speed parameter: positive sets it, -2 returns to the default
    /// (CRUISE_SPEED, WPNAV_SPEED, AIRSPEED_CRUISE), anything else changes nothing.
    fn change_speed(&mut self, speed: f32) -> bool {
        let new = if speed.is_finite() && speed > 0.0 {
            Some(f64::from(speed))
        } else if speed == -2.0 {
            None
        } else {
            return false;
        };
        if new != self.speed_override {
            self.speed_override = new;
            self.record(LogEvent::SpeedChanged {
                speed: new.unwrap_or(0.0),
            });
        }
        true
    }

    /// Makes `seq` (or the first navigation item from it) the current item and
    /// memorises its position; ends the mission when there is none.
    fn go_to_index(&mut self, seq: u16, cause: &str, out: &mut Vec<MavMessage>) {
        let count = self.mission.count();
        let mut next = if self.profile.item0_is_home() {
            seq.max(1)
        } else {
            seq
        };
        while next < count && !is_nav(self.mission.items()[usize::from(next)].command) {
            let item = self.mission.items()[usize::from(next)].clone();
            self.do_item(next, &item);
            next += 1;
        }
        if next >= count {
            self.finish_mission(out);
            return;
        }
        self.current = next;
        self.target = self.target_of(next);
        if !(self.quiet_progress && cause == "advance") {
            out.push(self.mission_current());
        }
        self.record(LogEvent::CurrentChanged {
            seq: next,
            cause: cause.to_owned(),
        });
    }

    /// Where a NAV_LAND steers the vehicle this step. A copter flies to the point at its
    /// altitude, then descends straight down (ArduCopter's NAV_LAND); a plane glides on the
    /// straight slope from where the item began to the touchdown point (ArduPlane's
    /// approach), so an approach that starts too high or too close touches down long.
    fn landing_aim(&self, t: &Target) -> Ned {
        let ground = Ned { up: 0.0, ..t.pos };
        match self.cfg.kind {
            VehicleKind::Copter => {
                if self.state.pos.horizontal_distance(&ground) > self.wp_radius() {
                    Ned {
                        up: self.state.pos.up,
                        ..ground
                    }
                } else {
                    ground
                }
            }
            _ => {
                // Along the approach line from `from` to the touchdown point: the height the
                // slope asks for here, a metre under the ground at the point so the wheels
                // meet it before; past the point the plane keeps descending ahead (it lands
                // long) instead of turning back.
                let total = t.from.horizontal_distance(&ground).max(1.0);
                let (un, ue) = (
                    (ground.north - t.from.north) / total,
                    (ground.east - t.from.east) / total,
                );
                let along = (self.state.pos.north - t.from.north) * un
                    + (self.state.pos.east - t.from.east) * ue;
                let left = total - along;
                let ahead = if left > 0.0 { 0.0 } else { 1_000.0 };
                Ned {
                    north: ground.north + un * ahead,
                    east: ground.east + ue * ahead,
                    up: t.from.up * (left / total).clamp(0.0, 1.0) - 1.0,
                }
            }
        }
    }

    /// A NAV_LAND touched the ground: the item is reached where the wheels are, and the
    /// autopilot disarms (ArduCopter at once; ArduPlane after LAND_DISARMDELAY, shortened
    /// here to touchdown, since a plane rolling to a stop changes nothing a test looks at).
    fn touch_down(&mut self, t: Target, out: &mut Vec<MavMessage>) {
        self.state.pos.up = 0.0;
        self.record(LogEvent::Landed);
        out.push(statustext(MavSeverity::MAV_SEVERITY_INFO, "Land complete"));
        self.set_armed(false, out);
        self.reached(t, out);
    }

    fn finish_mission(&mut self, out: &mut Vec<MavMessage>) {
        let last = self.target.map_or(self.current, |t| t.seq);
        self.target = None;
        self.hold_point = self.state.pos;
        out.push(statustext(
            MavSeverity::MAV_SEVERITY_INFO,
            "Mission Complete",
        ));
        self.record(LogEvent::MissionComplete { seq: last });
        // A mission that ended with a landing leaves the vehicle on the ground, disarmed, in
        // AUTO: nothing to loiter over.
        if !self.armed {
            return;
        }
        if let Some(mode) = modes::mission_complete(self.cfg.kind) {
            self.change_mode(mode, out);
        }
    }

    fn reached(&mut self, t: Target, out: &mut Vec<MavMessage>) {
        if !self.quiet_progress {
            out.push(MavMessage::MISSION_ITEM_REACHED(
                MISSION_ITEM_REACHED_DATA { seq: t.seq },
            ));
            let dist = self.state.pos.horizontal_distance(&t.pos);
            let text = match self.cfg.kind {
                VehicleKind::Rover => format!("Reached waypoint #{}", t.seq),
                VehicleKind::Copter => format!("Reached command #{}", t.seq),
                VehicleKind::Plane => {
                    format!("Reached waypoint #{} dist {}m", t.seq, dist.round())
                }
            };
            out.push(statustext(MavSeverity::MAV_SEVERITY_INFO, &text));
        }
        self.record(LogEvent::ItemReached {
            seq: t.seq,
            lat: t.lat,
            lon: t.lon,
        });
        // The next index of whatever mission is on board *now* (003 §2.5.4).
        self.target = None;
        if self.late_advance_s > 0.0 {
            self.hold_point = self.state.pos;
            self.pending_advance = Some((self.sim_time + self.late_advance_s, t.seq + 1));
            return;
        }
        self.go_to_index(t.seq + 1, "advance", out);
    }

    /// Sets the current mission index (MISSION_SET_CURRENT / DO_SET_MISSION_CURRENT).
    fn set_current(&mut self, seq: u16, out: &mut Vec<MavMessage>) -> bool {
        if seq >= self.mission.count() {
            return false;
        }
        let first = u16::from(self.profile.item0_is_home());
        let seq = seq.max(first).min(self.mission.count().saturating_sub(1));
        if seq == 0 && first == 1 {
            return false;
        }
        let driving = self.behaviour() == Behaviour::Auto;
        if seq == self.current && (!driving || self.target_seq() == Some(seq)) {
            // Already there (a ground station resending over a lossy link): nothing changes,
            // and an autopilot that reports only changes says nothing.
            if !self.profile.mission_current_on_change_only() {
                out.push(self.mission_current());
            }
            return true;
        }
        if self.behaviour() == Behaviour::Auto {
            self.go_to_index(seq, "set_current", out);
        } else {
            self.current = seq;
            out.push(self.mission_current());
            self.record(LogEvent::CurrentChanged {
                seq,
                cause: "set_current".to_owned(),
            });
        }
        true
    }

    /// Changes mode; returns the COMMAND_ACK result.
    fn change_mode(&mut self, mode: u32, out: &mut Vec<MavMessage>) -> MavResult {
        let Some((_, name, behaviour)) = modes::lookup(self.cfg.kind, mode) else {
            return MavResult::MAV_RESULT_DENIED;
        };
        if behaviour == Behaviour::Auto && self.mission.count() <= 1 {
            out.push(statustext(
                MavSeverity::MAV_SEVERITY_WARNING,
                "No Mission. Can't set AUTO.",
            ));
            return MavResult::MAV_RESULT_FAILED;
        }
        if mode == self.mode {
            return MavResult::MAV_RESULT_ACCEPTED;
        }
        let from = self.mode;
        self.mode = mode;
        self.hold_point = self.state.pos;
        self.takeoff_to = None;
        self.guided_to = None;
        if behaviour == Behaviour::Takeoff {
            // ArduPlane's TAKEOFF mode: climb ahead on the present heading to TKOFF_ALT.
            let alt = f64::from(self.params.get_or("TKOFF_ALT", 50.0));
            let ahead = 10_000.0;
            self.takeoff_to = Some(Ned {
                north: self.state.pos.north + ahead * self.state.yaw.cos(),
                east: self.state.pos.east + ahead * self.state.yaw.sin(),
                up: alt,
            });
        }
        self.reposition = None;
        if self.speed_override.take().is_some() {
            self.record(LogEvent::SpeedChanged { speed: 0.0 });
        }
        self.record(LogEvent::ModeChanged {
            from,
            to: mode,
            name: name.to_owned(),
        });
        if behaviour == Behaviour::Auto {
            let first = u16::from(self.profile.item0_is_home());
            let start = if self.current < first || self.current >= self.mission.count() {
                first
            } else {
                self.current
            };
            self.go_to_index(start, "auto_start", out);
        }
        out.push(self.heartbeat());
        MavResult::MAV_RESULT_ACCEPTED
    }

    fn set_armed(&mut self, armed: bool, out: &mut Vec<MavMessage>) {
        if armed != self.armed {
            self.armed = armed;
            self.record(LogEvent::Armed { armed });
            out.push(statustext(
                MavSeverity::MAV_SEVERITY_INFO,
                if armed {
                    "Throttle armed"
                } else {
                    "Throttle disarmed"
                },
            ));
            out.push(self.heartbeat());
        }
    }

    // ---------------------------------------------------------------- time

    /// Advances the simulation by `dt` seconds (a fixed step).
    pub fn step(&mut self, dt: f64) -> Vec<MavMessage> {
        let mut out = Vec::new();
        self.sim_time += dt;
        if let Some((due, seq)) = self.pending_advance {
            if self.sim_time >= due {
                self.pending_advance = None;
                if self.behaviour() == Behaviour::Auto {
                    self.go_to_index(seq, "late advance", &mut out);
                }
            }
        }
        if !self.armed {
            self.battery.drain(dt, 0.0, false);
            self.state.speed = 0.0;
            self.state.vel_north = 0.0;
            self.state.vel_east = 0.0;
            self.state.climb = 0.0;
            self.state.yaw_rate = 0.0;
            return out;
        }
        let limits = self.limits();
        let command = match self.behaviour() {
            Behaviour::Manual => {
                // No override: sticks centred (a copter hovers), a plane's throttle at idle
                // (its bottom: on the ground it stands still).
                let idle = Sticks {
                    steer: 0.0,
                    throttle: if self.cfg.kind == VehicleKind::Plane {
                        -1.0
                    } else {
                        0.0
                    },
                };
                let s = self.sticks.map_or(idle, |(s, _)| s);
                Command::Sticks {
                    steer: s.steer,
                    throttle: s.throttle,
                }
            }
            Behaviour::Auto => match self.target {
                Some(t) if t.land => Command::GoTo(self.landing_aim(&t)),
                Some(t) => Command::GoTo(t.pos),
                None => Command::Hold(self.hold_point),
            },
            Behaviour::Rtl => {
                let home = Ned {
                    up: self
                        .state
                        .pos
                        .up
                        .max(if self.cfg.kind == VehicleKind::Rover {
                            0.0
                        } else {
                            15.0
                        }),
                    ..Ned::default()
                };
                if self.state.pos.horizontal_distance(&home) <= self.wp_radius() {
                    Command::Hold(home)
                } else {
                    Command::GoTo(home)
                }
            }
            Behaviour::Guided | Behaviour::Takeoff => match self.takeoff_to.or(self.guided_to) {
                Some(t) => Command::GoTo(t),
                None => Command::Hold(self.hold_point),
            },
            Behaviour::Land => Command::GoTo(Ned {
                up: 0.0,
                ..self.hold_point
            }),
            Behaviour::Hold => match self.reposition {
                Some((p, _)) => Command::GoTo(p),
                None => Command::Hold(self.hold_point),
            },
        };
        let before = self.state.pos;
        self.state.step(self.cfg.kind, command, &limits, dt);
        let moved =
            before.horizontal_distance(&self.state.pos) + (self.state.pos.up - before.up).abs();
        self.battery.drain(dt, moved, true);
        self.check_fence(&mut out);
        if self.behaviour() == Behaviour::Auto {
            if let Some(t) = self.target {
                if t.land {
                    if self.state.pos.up <= TOUCHDOWN_M {
                        self.touch_down(t, &mut out);
                    }
                } else if self.within(&t.pos, t.radius.unwrap_or_else(|| self.wp_radius())) {
                    self.reached(t, &mut out);
                }
            }
        }
        if self.behaviour() == Behaviour::Land && self.state.pos.up <= 0.05 {
            // ArduCopter disarms once LAND touches down.
            self.record(LogEvent::Landed);
            self.set_armed(false, &mut out);
        }
        if let Some((p, geo)) = self
            .reposition
            .filter(|_| self.behaviour() == Behaviour::Hold)
        {
            if self.within(&p, self.wp_radius()) {
                self.reposition = None;
                self.hold_point = p;
                self.record(LogEvent::RepositionReached {
                    lat: geo.lat_deg,
                    lon: geo.lon_deg,
                });
            }
        }
        if let Some(t) = self
            .guided_to
            .filter(|_| self.behaviour() == Behaviour::Guided)
        {
            if self.within(&t, self.wp_radius()) {
                self.guided_to = None;
                self.hold_point = t;
            }
        }
        if let Some(t) = self
            .takeoff_to
            .filter(|_| matches!(self.behaviour(), Behaviour::Guided | Behaviour::Takeoff))
        {
            if (self.state.pos.up - t.up).abs() <= 0.5 {
                self.takeoff_to = None;
                self.hold_point = self.state.pos;
                self.record(LogEvent::TakeoffComplete {
                    alt: self.state.pos.up,
                });
            }
        }
        out
    }

    /// Enforces the fence: on a breach, a STATUSTEXT (critical, `Fence breached: {why};
    /// {action}`), a log record and the family's action: ArduPilot's `FENCE_ACTION` (rover: 0
    /// report, 1 RTL, 2 hold), PX4's `GF_ACTION` (see [`Self::px4_fence_action`]).
    fn check_fence(&mut self, out: &mut Vec<MavMessage>) {
        let px4 = self.profile == Profile::Px4;
        let p = if px4 {
            self.px4_fence()
        } else {
            self.ardupilot_fence()
        };
        let Some(why) = self.fence.breach(&p, &self.state.pos) else {
            return;
        };
        let (mode, action) = if px4 {
            self.px4_fence_action()
        } else {
            self.ardupilot_fence_action()
        };
        let here = self.frame.to_geo(self.state.pos);
        out.push(statustext(
            MavSeverity::MAV_SEVERITY_CRITICAL,
            &format!("Fence breached: {why}; {action}"),
        ));
        self.record(LogEvent::FenceBreached {
            fence: why,
            action,
            lat: here.lat_deg,
            lon: here.lon_deg,
        });
        if let Some(number) = mode {
            self.change_mode(number, out);
        }
    }

    /// The first mode of the table that behaves as `b`: its number and lower-case name.
    fn mode_for(&self, b: Behaviour) -> Option<(u32, String)> {
        modes::table(self.cfg.kind)
            .iter()
            .find(|m| m.2 == b)
            .map(|m| (m.0, m.1.to_ascii_lowercase()))
    }

    /// ArduPilot's fence (all profiles but PX4's): `FENCE_ENABLE`, `FENCE_TYPE`,
    /// `FENCE_RADIUS`, `FENCE_ALT_MAX`.
    fn ardupilot_fence(&self) -> FenceParams {
        FenceParams {
            enabled: self.params.get_or("FENCE_ENABLE", 0.0) >= 1.0,
            kinds: self.params.get_or("FENCE_TYPE", 0.0).clamp(0.0, 255.0) as u8,
            radius_m: f64::from(self.params.get_or("FENCE_RADIUS", 0.0)),
            alt_max_m: f64::from(self.params.get_or("FENCE_ALT_MAX", 0.0)),
        }
    }

    /// ArduPilot's breach action, `FENCE_ACTION` (rover: 0 report, 1 RTL, 2 hold): the mode to
    /// enter, if any, and the action's name.
    fn ardupilot_fence_action(&self) -> (Option<u32>, String) {
        let wanted = match self.params.get_or("FENCE_ACTION", 1.0).round() as i64 {
            0 => None,
            2 => Some(Behaviour::Hold),
            _ => Some(Behaviour::Rtl),
        };
        match wanted.and_then(|b| self.mode_for(b)) {
            Some((number, name)) => (Some(number), name),
            None => (None, "report".to_owned()),
        }
    }

    /// PX4's geofence: in force when an area is on board or `GF_MAX_HOR_DIST` /
    /// `GF_MAX_VER_DIST` is set, unless `GF_ACTION` is 0.
    fn px4_fence(&self) -> FenceParams {
        let (hor, ver) = (
            f64::from(self.params.get_or("GF_MAX_HOR_DIST", 0.0)),
            f64::from(self.params.get_or("GF_MAX_VER_DIST", 0.0)),
        );
        let gf_action = self.params.get_or("GF_ACTION", 2.0).round() as i64;
        FenceParams {
            enabled: gf_action != 0 && (self.fence.has_area() || hor > 0.0 || ver > 0.0),
            kinds: 4 | u8::from(ver > 0.0) | (u8::from(hor > 0.0) << 1),
            radius_m: hor,
            alt_max_m: ver,
        }
    }

    /// PX4's breach action, `GF_ACTION`: 1 warning (report only), 2 hold (the kind's hold
    /// mode; also any other value), 3 return (RTL), 5 land (LAND where the kind has it, else
    /// hold), 4 terminate (not simulated: as 5, named `terminate as <mode>`).
    fn px4_fence_action(&self) -> (Option<u32>, String) {
        let hold = modes::hold(self.cfg.kind);
        let hold = (hold, modes::name(self.cfg.kind, hold).to_ascii_lowercase());
        let land = || {
            self.mode_for(Behaviour::Land)
                .unwrap_or_else(|| hold.clone())
        };
        match self.params.get_or("GF_ACTION", 2.0).round() as i64 {
            1 => (None, "warning".to_owned()),
            3 => {
                let (number, name) = self
                    .mode_for(Behaviour::Rtl)
                    .unwrap_or_else(|| hold.clone());
                (Some(number), name)
            }
            4 => {
                let (number, name) = land();
                (Some(number), format!("terminate as {name}"))
            }
            5 => {
                let (number, name) = land();
                (Some(number), name)
            }
            _ => (Some(hold.0), hold.1.clone()),
        }
    }

    /// Within `radius` of `p` (and, for a copter, of its altitude).
    fn within(&self, p: &Ned, radius: f64) -> bool {
        self.state.pos.horizontal_distance(p) <= radius
            && (self.cfg.kind != VehicleKind::Copter || (self.state.pos.up - p.up).abs() <= radius)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::ardupilotmega::{MISSION_COUNT_DATA, MISSION_SET_CURRENT_DATA};

    const HOME: GeoPoint = GeoPoint {
        lat_deg: 41.2757,
        lon_deg: 1.9881,
        alt_m: 10.0,
    };
    pub(super) const GCS: (u8, u8) = (255, 190);

    pub(super) fn rover() -> Vehicle {
        Vehicle::new(
            VehicleConfig {
                kind: VehicleKind::Rover,
                sysid: 1,
                home: HOME,
            },
            Instant::now(),
        )
    }

    /// Item `seq` at `north` metres north of home (a straight line of waypoints).
    fn item_at(v: &Vehicle, seq: u16, north: f64) -> Item {
        let geo = v.frame.to_geo(Ned {
            north,
            east: 0.0,
            up: 0.0,
        });
        Item {
            seq,
            x: (geo.lat_deg * 1e7).round() as i32,
            y: (geo.lon_deg * 1e7).round() as i32,
            command: MavCmd::MAV_CMD_NAV_WAYPOINT,
            frame: MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT,
            ..Item::default()
        }
    }

    pub(super) fn upload(v: &mut Vehicle, norths: &[f64]) {
        let now = Instant::now();
        let count = norths.len() as u16 + 1;
        v.handle(
            GCS,
            &MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
                count,
                ..Default::default()
            }),
            now,
        );
        for seq in 0..count {
            let north = if seq == 0 {
                0.0
            } else {
                norths[usize::from(seq) - 1]
            };
            let item = item_at(v, seq, north);
            v.handle(GCS, &MavMessage::MISSION_ITEM_INT(item), now);
        }
        assert_eq!(v.mission().len(), usize::from(count));
    }

    fn partial(v: &mut Vehicle, seq: u16, north: f64) {
        let now = Instant::now();
        let msg = MavMessage::MISSION_WRITE_PARTIAL_LIST(
            mavlink::dialects::ardupilotmega::MISSION_WRITE_PARTIAL_LIST_DATA {
                start_index: seq as i16,
                end_index: seq as i16,
                ..Default::default()
            },
        );
        v.handle(GCS, &msg, now);
        let item = item_at(v, seq, north);
        v.handle(GCS, &MavMessage::MISSION_ITEM_INT(item), now);
    }

    pub(super) fn command(v: &mut Vehicle, command: MavCmd, p1: f32, p2: f32) -> MavResult {
        command_long(
            v,
            COMMAND_LONG_DATA {
                command,
                param1: p1,
                param2: p2,
                ..Default::default()
            },
        )
    }

    /// Sends `cmd` and returns the result its COMMAND_ACK carries.
    pub(super) fn command_long(v: &mut Vehicle, cmd: COMMAND_LONG_DATA) -> MavResult {
        let out = v.handle(GCS, &MavMessage::COMMAND_LONG(cmd), Instant::now());
        out.iter()
            .find_map(|m| match m {
                MavMessage::COMMAND_ACK(a) => Some(a.result),
                _ => None,
            })
            .unwrap()
    }

    fn reached_seqs(v: &mut Vehicle) -> Vec<u16> {
        v.take_log()
            .into_iter()
            .filter_map(|(_, e)| match e {
                LogEvent::ItemReached { seq, .. } => Some(seq),
                _ => None,
            })
            .collect()
    }

    /// Steps until `f` holds (at most `max_s` simulated seconds).
    pub(super) fn run_until(v: &mut Vehicle, max_s: f64, mut f: impl FnMut(&Vehicle) -> bool) {
        let mut t = 0.0;
        while !f(v) {
            v.step(0.02);
            t += 0.02;
            assert!(t < max_s, "condition not met after {max_s} s");
        }
    }

    pub(super) fn start_auto(v: &mut Vehicle) {
        assert_eq!(
            command(v, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert_eq!(
            command(v, MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 10.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
    }

    #[test]
    fn copter_and_plane_fly_the_mission_in_order() {
        for (kind, spacing, auto, max_s) in [
            (VehicleKind::Copter, 30.0, 3.0, 200.0),
            (VehicleKind::Plane, 400.0, 10.0, 600.0),
        ] {
            let mut v = Vehicle::new(
                VehicleConfig {
                    kind,
                    sysid: 1,
                    home: HOME,
                },
                Instant::now(),
            );
            upload(&mut v, &[spacing, 2.0 * spacing, 3.0 * spacing]);
            assert_eq!(
                command(&mut v, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0),
                MavResult::MAV_RESULT_ACCEPTED
            );
            assert_eq!(
                command(&mut v, MavCmd::MAV_CMD_DO_SET_MODE, 1.0, auto),
                MavResult::MAV_RESULT_ACCEPTED
            );
            run_until(&mut v, max_s, |v| v.target_seq().is_none());
            assert_eq!(reached_seqs(&mut v), vec![1, 2, 3], "{kind:?}");
        }
    }

    pub(super) fn copter() -> Vehicle {
        Vehicle::new(
            VehicleConfig {
                kind: VehicleKind::Copter,
                sysid: 1,
                home: HOME,
            },
            Instant::now(),
        )
    }

    fn upload_items(v: &mut Vehicle, items: &[Item]) {
        let now = Instant::now();
        let count = items.len() as u16 + 1;
        v.handle(
            GCS,
            &MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
                count,
                ..Default::default()
            }),
            now,
        );
        let home = item_at(v, 0, 0.0);
        v.handle(GCS, &MavMessage::MISSION_ITEM_INT(home), now);
        for (i, item) in items.iter().enumerate() {
            let item = Item {
                seq: i as u16 + 1,
                ..item.clone()
            };
            v.handle(GCS, &MavMessage::MISSION_ITEM_INT(item), now);
        }
        assert_eq!(v.mission().len(), usize::from(count));
    }

    fn takeoff_command(v: &mut Vehicle, alt: f32) -> MavResult {
        command_long(
            v,
            COMMAND_LONG_DATA {
                command: MavCmd::MAV_CMD_NAV_TAKEOFF,
                param7: alt,
                ..Default::default()
            },
        )
    }

    #[test]
    fn copter_takes_off_in_guided_then_holds() {
        let mut v = copter();
        // Disarmed, or not in GUIDED: refused, as ArduCopter does.
        command(&mut v, MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 4.0);
        assert_eq!(takeoff_command(&mut v, 10.0), MavResult::MAV_RESULT_FAILED);
        command(&mut v, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0);
        command(&mut v, MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 0.0);
        assert_eq!(takeoff_command(&mut v, 10.0), MavResult::MAV_RESULT_FAILED);
        command(&mut v, MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 4.0);
        assert_eq!(
            takeoff_command(&mut v, f32::NAN),
            MavResult::MAV_RESULT_DENIED
        );
        assert_eq!(
            takeoff_command(&mut v, 10.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        run_until(&mut v, 30.0, |v| (v.position().up - 10.0).abs() < 0.5);
        let done = v.take_log().into_iter().any(
            |(_, e)| matches!(e, LogEvent::TakeoffComplete { alt } if (alt - 10.0).abs() < 0.5),
        );
        assert!(done, "take-off logged");
        // Straight up, and it stays there.
        for _ in 0..500 {
            v.step(0.02);
        }
        let p = v.position();
        assert!(
            p.north.hypot(p.east) < 0.1 && (p.up - 10.0).abs() < 0.5,
            "{p:?}"
        );
        // Airborne: a second take-off is refused.
        assert_eq!(takeoff_command(&mut v, 20.0), MavResult::MAV_RESULT_FAILED);
    }

    #[test]
    fn guided_flies_to_a_repositioned_point_then_land_descends_and_disarms() {
        let mut v = copter();
        command(&mut v, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0);
        command(&mut v, MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 4.0);
        assert_eq!(
            takeoff_command(&mut v, 10.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        run_until(&mut v, 30.0, |v| (v.position().up - 10.0).abs() < 0.5);
        // 100 m east at 30 m above home (the altitude is MSL: home is 10 m).
        let east = v.frame.to_geo(Ned {
            north: 0.0,
            east: 100.0,
            up: 0.0,
        });
        let reposition = |lat: f64| COMMAND_LONG_DATA {
            command: MavCmd::MAV_CMD_DO_REPOSITION,
            param1: 5.0,
            param5: lat as f32,
            param6: east.lon_deg as f32,
            param7: 40.0,
            ..Default::default()
        };
        assert_eq!(
            command_long(&mut v, reposition(f64::NAN)),
            MavResult::MAV_RESULT_DENIED
        );
        assert_eq!(
            command_long(&mut v, reposition(east.lat_deg)),
            MavResult::MAV_RESULT_ACCEPTED
        );
        run_until(&mut v, 60.0, |v| {
            let p = v.position();
            (p.east - 100.0).abs() < 2.0 && (p.up - 30.0).abs() < 2.0
        });
        // LAND: straight down where it is, disarmed on the ground; no arming in LAND.
        command(&mut v, MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 9.0);
        run_until(&mut v, 60.0, |v| !v.armed());
        let p = v.position();
        assert!(p.up < 0.1 && (p.east - 100.0).abs() < 5.0, "{p:?}");
        assert!(v.take_log().iter().any(|(_, e)| *e == LogEvent::Landed));
        assert_eq!(
            command(&mut v, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0),
            MavResult::MAV_RESULT_FAILED
        );
        // Outside GUIDED a reposition is refused.
        assert_eq!(
            command_long(&mut v, reposition(east.lat_deg)),
            MavResult::MAV_RESULT_FAILED
        );
    }

    #[test]
    fn plane_takeoff_mode_climbs_to_tkoff_alt() {
        let mut v = Vehicle::new(
            VehicleConfig {
                kind: VehicleKind::Plane,
                sysid: 1,
                home: HOME,
            },
            Instant::now(),
        );
        command(&mut v, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0);
        assert_eq!(
            command(&mut v, MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 13.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        run_until(&mut v, 300.0, |v| (v.position().up - 50.0).abs() < 0.5);
        assert!(v
            .take_log()
            .iter()
            .any(|(_, e)| matches!(e, LogEvent::TakeoffComplete { .. })));
    }

    #[test]
    fn takeoff_item_climbs_where_the_copter_stands() {
        let mut v = copter();
        // A NAV_TAKEOFF whose lat/lon point 50 m north: ArduCopter ignores them.
        let takeoff = Item {
            command: MavCmd::MAV_CMD_NAV_TAKEOFF,
            z: 15.0,
            ..item_at(&v, 1, 50.0)
        };
        let wp = Item {
            z: 15.0,
            ..item_at(&v, 2, 30.0)
        };
        upload_items(&mut v, &[takeoff, wp]);
        command(&mut v, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0);
        command(&mut v, MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 3.0);
        run_until(&mut v, 60.0, |v| v.current() == 2);
        let p = v.position();
        assert!(p.north.hypot(p.east) < 1.0, "climbed in place: {p:?}");
        assert!((p.up - 15.0).abs() <= 2.0, "{p:?}");
        run_until(&mut v, 120.0, |v| v.target_seq().is_none());
        assert_eq!(reached_seqs(&mut v), vec![1, 2]);
    }

    #[test]
    fn an_autopilot_still_checking_itself_answers_temporarily_rejected_then_accepts() {
        let mut v = rover();
        v.set_not_ready_for(2.0);
        for (cmd, p1, p2) in [
            (MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 0.0),
            (MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0),
        ] {
            assert_eq!(
                command(&mut v, cmd, p1, p2),
                MavResult::MAV_RESULT_TEMPORARILY_REJECTED
            );
        }
        for _ in 0..101 {
            v.step(0.02);
        }
        assert_eq!(
            command(&mut v, MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 0.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert_eq!(
            command(&mut v, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
    }

    #[test]
    fn a_mission_ending_in_nav_land_lands_the_copter_at_the_point_and_disarms() {
        let mut v = copter();
        let takeoff = Item {
            command: MavCmd::MAV_CMD_NAV_TAKEOFF,
            z: 20.0,
            ..item_at(&v, 1, 0.0)
        };
        let out = Item {
            z: 20.0,
            ..item_at(&v, 2, 80.0)
        };
        let land = Item {
            command: MavCmd::MAV_CMD_NAV_LAND,
            ..item_at(&v, 3, 40.0)
        };
        upload_items(&mut v, &[takeoff, out, land]);
        command(&mut v, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0);
        command(&mut v, MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 3.0);
        run_until(&mut v, 60.0, |v| v.current() == 3);
        // It flies to the landing point at its altitude, then descends straight down.
        run_until(&mut v, 60.0, |v| (v.position().north - 40.0).abs() < 2.0);
        assert!(v.position().up > 15.0, "{:?}", v.position());
        run_until(&mut v, 60.0, |v| !v.armed());
        let p = v.position();
        assert!(p.up < 0.1 && (p.north - 40.0).abs() < 2.5, "{p:?}");
        let log = v.take_log();
        let reached: Vec<u16> = log
            .iter()
            .filter_map(|(_, e)| match e {
                LogEvent::ItemReached { seq, .. } => Some(*seq),
                _ => None,
            })
            .collect();
        assert_eq!(reached, [1, 2, 3]);
        assert!(log.iter().any(|(_, e)| *e == LogEvent::Landed));
        assert!(log
            .iter()
            .any(|(_, e)| matches!(e, LogEvent::MissionComplete { .. })));
        // On the ground it stays, disarmed, in AUTO: no loiter over the runway.
        assert_eq!(v.mode, 3);
        for _ in 0..100 {
            v.step(0.02);
        }
        assert_eq!(v.position().up, 0.0);
    }

    #[test]
    fn a_plane_glides_down_the_approach_and_a_steep_one_lands_long() {
        let plane = || {
            Vehicle::new(
                VehicleConfig {
                    kind: VehicleKind::Plane,
                    sysid: 1,
                    home: HOME,
                },
                Instant::now(),
            )
        };
        // (approach start north of home, its height, how far past the point it may land)
        for (start, height, long_m) in [(1_200.0, 60.0, 20.0), (300.0, 150.0, 100.0)] {
            let mut v = plane();
            let faf = Item {
                z: height,
                ..item_at(&v, 1, start)
            };
            let land = Item {
                command: MavCmd::MAV_CMD_NAV_LAND,
                ..item_at(&v, 2, 0.0)
            };
            upload_items(&mut v, &[faf, land]);
            // Airborne at the approach height, heading south toward the runway.
            v.state.pos = Ned {
                north: start + 300.0,
                east: 0.0,
                up: f64::from(height),
            };
            v.state.yaw = std::f64::consts::PI;
            command(&mut v, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0);
            command(&mut v, MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 10.0);
            run_until(&mut v, 600.0, |v| !v.armed());
            let p = v.position();
            assert_eq!(reached_seqs(&mut v), vec![1, 2]);
            assert!(p.up == 0.0 && p.east.abs() < 5.0, "{p:?}");
            if long_m < 50.0 {
                assert!(
                    p.north.abs() < long_m,
                    "a gentle slope lands on the point: {p:?}"
                );
            } else {
                assert!(-p.north > 50.0, "too steep a slope lands long: {p:?}");
            }
        }
    }

    #[test]
    fn do_change_speed_item_and_command() {
        let mut v = rover();
        let speed = Item {
            command: MavCmd::MAV_CMD_DO_CHANGE_SPEED,
            param1: 1.0,
            param2: 4.0,
            param3: -1.0,
            x: 0,
            y: 0,
            ..Item::default()
        };
        let items = [
            item_at(&v, 1, 20.0),
            speed,
            item_at(&v, 3, 120.0),
            item_at(&v, 4, 220.0),
        ];
        upload_items(&mut v, &items);
        start_auto(&mut v);
        let mut fastest_before = 0.0f64;
        run_until(&mut v, 60.0, |v| {
            fastest_before = fastest_before.max(v.state.speed);
            v.current() == 3
        });
        assert!(fastest_before <= 2.01, "cruise before: {fastest_before}");
        run_until(&mut v, 60.0, |v| v.state.speed > 3.9);
        // The command works too; -2 goes back to CRUISE_SPEED.
        assert_eq!(
            command(&mut v, MavCmd::MAV_CMD_DO_CHANGE_SPEED, 1.0, 1.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        run_until(&mut v, 30.0, |v| v.state.speed < 1.01);
        command(&mut v, MavCmd::MAV_CMD_DO_CHANGE_SPEED, 1.0, -2.0);
        run_until(&mut v, 30.0, |v| v.state.speed > 1.99);
        let speeds: Vec<f64> = v
            .take_log()
            .into_iter()
            .filter_map(|(_, e)| match e {
                LogEvent::SpeedChanged { speed } => Some(speed),
                _ => None,
            })
            .collect();
        assert_eq!(speeds, [4.0, 1.0, 0.0]);
    }

    #[test]
    fn acceptance_radius_per_item() {
        // Fly-by with a wide radius turns early; the default WP_RADIUS passes almost over it.
        for (radius, reached_at) in [(0.0f32, 18.0), (8.0, 12.0)] {
            let mut v = rover();
            let wp = Item {
                param2: radius,
                ..item_at(&v, 1, 20.0)
            };
            let next = item_at(&v, 2, 60.0);
            upload_items(&mut v, &[wp, next]);
            start_auto(&mut v);
            run_until(&mut v, 60.0, |v| v.current() == 2);
            let north = v.position().north;
            assert!(
                (north - reached_at).abs() < 0.5,
                "radius {radius}: reached at {north}"
            );
        }
    }

    #[test]
    fn quiet_progress_reports_nothing_but_set_current() {
        let mut v = rover();
        v.set_quiet_progress(true);
        upload(&mut v, &[10.0, 20.0, 30.0]);
        start_auto(&mut v);
        let mut told = Vec::new();
        let mut t = 0.0;
        while v.mode() != 4 {
            told.extend(v.step(0.02));
            t += 0.02;
            assert!(t < 120.0, "mission not flown");
        }
        told.extend(v.poll(Instant::now() + Duration::from_secs(5)));
        assert!(told.len() > 3, "{told:?}");
        assert!(
            !told.iter().any(|m| matches!(
                m,
                MavMessage::MISSION_ITEM_REACHED(_)
                    | MavMessage::MISSION_CURRENT(_)
                    | MavMessage::STATUSTEXT(_)
            ) && !matches!(m, MavMessage::STATUSTEXT(t) if t.text.to_str().unwrap_or("") == "Mission Complete")),
            "{told:?}"
        );
        // The vehicle still flew the mission, and a set-current is still answered.
        assert_eq!(reached_seqs(&mut v), vec![1, 2, 3]);
        let out = v.handle(
            GCS,
            &MavMessage::MISSION_SET_CURRENT(MISSION_SET_CURRENT_DATA {
                seq: 2,
                ..Default::default()
            }),
            Instant::now(),
        );
        assert!(out
            .iter()
            .any(|m| matches!(m, MavMessage::MISSION_CURRENT(c) if c.seq == 2)));
    }

    #[test]
    fn auto_needs_a_mission() {
        let mut v = rover();
        assert_eq!(
            command(&mut v, MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 10.0),
            MavResult::MAV_RESULT_FAILED
        );
        assert_eq!(
            command(&mut v, MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 77.0),
            MavResult::MAV_RESULT_DENIED
        );
        assert_eq!(v.mode(), 0);
    }

    #[test]
    fn drives_the_mission_in_order_then_holds() {
        let mut v = rover();
        upload(&mut v, &[10.0, 20.0, 30.0]);
        start_auto(&mut v);
        assert_eq!(v.current(), 1);
        run_until(&mut v, 120.0, |v| v.mode() == 4);
        assert_eq!(reached_seqs(&mut v), vec![1, 2, 3]);
        assert!(v.target_seq().is_none());
    }

    #[test]
    fn new_upload_keeps_the_memorised_target() {
        let mut v = rover();
        upload(&mut v, &[20.0, 40.0, 60.0]);
        start_auto(&mut v);
        run_until(&mut v, 60.0, |v| v.position().north > 5.0);
        // A new plan far to the south; the rover still drives to the old item 1.
        upload(&mut v, &[-100.0, -200.0]);
        assert_eq!(v.target_seq(), Some(1));
        run_until(&mut v, 60.0, |v| v.current() == 2);
        let pos = v.position();
        assert!(
            (pos.north - 20.0).abs() < 3.0,
            "reached the memorised item 1 at {pos:?}"
        );
        // Then it takes index 2 *of the new plan*.
        run_until(&mut v, 200.0, |v| v.mode() == 4);
        assert!((v.position().north + 200.0).abs() < 3.0);
        assert_eq!(reached_seqs(&mut v), vec![1, 2]);
    }

    #[test]
    fn set_current_changes_the_target_at_once() {
        let mut v = rover();
        upload(&mut v, &[20.0, 40.0, 60.0]);
        start_auto(&mut v);
        v.step(0.02);
        let out = v.handle(
            GCS,
            &MavMessage::MISSION_SET_CURRENT(MISSION_SET_CURRENT_DATA {
                seq: 3,
                ..Default::default()
            }),
            Instant::now(),
        );
        assert!(out
            .iter()
            .any(|m| matches!(m, MavMessage::MISSION_CURRENT(c) if c.seq == 3)));
        assert_eq!(v.target_seq(), Some(3));
        run_until(&mut v, 120.0, |v| v.mode() == 4);
        assert_eq!(reached_seqs(&mut v), vec![3]);
    }

    #[test]
    fn rolling_queue_never_stops() {
        // The 003 §3.3.2 loop: slots 1..=5, slot 5 equal to slot 1; each slot is
        // rewritten with the next plan waypoint once passed; when slot 4 is
        // reached (target now slot 5) set-current 1, which holds the same point.
        let mut v = rover();
        let spacing = 10.0;
        let wp = |n: u32| spacing * f64::from(n);
        upload(&mut v, &[wp(1), wp(2), wp(3), wp(4), wp(1)]);
        let mut next_wp = 5u32;
        start_auto(&mut v);
        let mut reached = Vec::new();
        let mut t = 0.0;
        while reached.len() < 20 {
            let out = v.step(0.02);
            t += 0.02;
            assert!(t < 600.0, "stalled after {reached:?}");
            assert_eq!(v.mode(), 10, "never leaves AUTO");
            for m in out {
                if let MavMessage::MISSION_ITEM_REACHED(r) = m {
                    reached.push(v.position().north);
                    let north = wp(next_wp);
                    next_wp += 1;
                    partial(&mut v, r.seq, north);
                    if r.seq == 1 {
                        partial(&mut v, 5, north);
                    }
                    if r.seq == 4 {
                        assert_eq!(v.current(), 5);
                        v.handle(
                            GCS,
                            &MavMessage::MISSION_SET_CURRENT(MISSION_SET_CURRENT_DATA {
                                seq: 1,
                                ..Default::default()
                            }),
                            Instant::now(),
                        );
                    }
                }
            }
        }
        // Every plan waypoint reached once, in order, at its place.
        for (i, north) in reached.iter().enumerate() {
            assert!(
                (north - wp(i as u32 + 1)).abs() < 3.0,
                "waypoint {} at {north}",
                i + 1
            );
        }
    }

    #[test]
    fn clear_all_lets_the_rover_finish_its_target_then_hold() {
        let mut v = rover();
        upload(&mut v, &[10.0, 20.0]);
        start_auto(&mut v);
        v.handle(
            GCS,
            &MavMessage::MISSION_CLEAR_ALL(Default::default()),
            Instant::now(),
        );
        run_until(&mut v, 60.0, |v| v.mode() == 4);
        assert!((v.position().north - 10.0).abs() < 3.0);
        assert_eq!(reached_seqs(&mut v), vec![1]);
    }

    #[test]
    fn disarmed_rover_does_not_move() {
        let mut v = rover();
        upload(&mut v, &[10.0]);
        assert_eq!(
            command(&mut v, MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 10.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        for _ in 0..500 {
            v.step(0.02);
        }
        assert_eq!(v.position(), Ned::default());
    }

    #[test]
    fn params_read_and_set() {
        let mut v = rover();
        let set = MavMessage::PARAM_SET(mavlink::dialects::ardupilotmega::PARAM_SET_DATA {
            param_value: 3.0,
            param_id: "WP_RADIUS".into(),
            ..Default::default()
        });
        let out = v.handle(GCS, &set, Instant::now());
        match &out[..] {
            [MavMessage::PARAM_VALUE(p)] => {
                assert_eq!(p.param_id.to_str().unwrap(), "WP_RADIUS");
                assert_eq!(p.param_value, 3.0);
            }
            other => panic!("{other:?}"),
        }
        let list = v.handle(
            GCS,
            &MavMessage::PARAM_REQUEST_LIST(Default::default()),
            Instant::now(),
        );
        assert_eq!(list.len(), v.params.len());
    }

    #[test]
    fn heartbeat_reports_mode_and_arming() {
        let mut v = rover();
        command(&mut v, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0);
        command(&mut v, MavCmd::MAV_CMD_DO_SET_MODE, 1.0, 4.0);
        match v.heartbeat() {
            MavMessage::HEARTBEAT(h) => {
                assert_eq!(h.custom_mode, 4);
                assert!(h
                    .base_mode
                    .contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED));
                assert!(h
                    .base_mode
                    .contains(MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED));
                assert_eq!(h.mavtype, MavType::MAV_TYPE_GROUND_ROVER);
            }
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn px4_profile_follows_px4_conventions() {
        let mut v = rover();
        v.set_profile(Profile::Px4);
        let hb = |v: &Vehicle| match v.heartbeat() {
            MavMessage::HEARTBEAT(h) => (h.autopilot, h.custom_mode),
            _ => unreachable!(),
        };
        assert_eq!(hb(&v).0, MavAutopilot::MAV_AUTOPILOT_PX4);
        // Item 0 is an ordinary item, kept as uploaded.
        let items: Vec<Item> = [10.0, 20.0, 30.0]
            .iter()
            .enumerate()
            .map(|(i, &n)| item_at(&v, i as u16, n))
            .collect();
        let now = Instant::now();
        v.handle(
            GCS,
            &MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
                count: 3,
                ..Default::default()
            }),
            now,
        );
        for item in &items {
            v.handle(GCS, &MavMessage::MISSION_ITEM_INT(item.clone()), now);
        }
        assert_eq!(v.mission().len(), 3);
        assert_eq!(v.mission()[0].x, items[0].x);
        // No partial writes: unanswered.
        let msg = MavMessage::MISSION_WRITE_PARTIAL_LIST(
            mavlink::dialects::ardupilotmega::MISSION_WRITE_PARTIAL_LIST_DATA {
                start_index: 1,
                end_index: 1,
                ..Default::default()
            },
        );
        assert!(v.handle(GCS, &msg, Instant::now()).is_empty());
        // AUTO.MISSION as PX4 names it: main 4, sub 4; the mission starts at item 0.
        assert_eq!(
            command(&mut v, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        let auto = command_long(
            &mut v,
            COMMAND_LONG_DATA {
                command: MavCmd::MAV_CMD_DO_SET_MODE,
                param1: 1.0,
                param2: 4.0,
                param3: 4.0,
                ..Default::default()
            },
        );
        assert_eq!(auto, MavResult::MAV_RESULT_ACCEPTED);
        assert_eq!(hb(&v).1, 4 << 16 | 4 << 24);
        assert_eq!(v.target_seq(), Some(0));
        run_until(&mut v, 60.0, |v| v.target_seq() == Some(2));
        assert_eq!(reached_seqs(&mut v), vec![0, 1]);
        // MISSION_CURRENT only on change: none streamed, none for a set-current to itself.
        assert!(v.telemetry(MISSION_CURRENT_ID).is_none());
        let same = MavMessage::MISSION_SET_CURRENT(MISSION_SET_CURRENT_DATA {
            seq: 2,
            ..Default::default()
        });
        assert!(v.handle(GCS, &same, Instant::now()).is_empty());
        // A whole upload resets the current item to 0, and the rover turns to it.
        let mut out = Vec::new();
        let now = Instant::now();
        out.extend(v.handle(
            GCS,
            &MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
                count: 3,
                ..Default::default()
            }),
            now,
        ));
        for item in &items {
            out.extend(v.handle(GCS, &MavMessage::MISSION_ITEM_INT(item.clone()), now));
        }
        assert!(out
            .iter()
            .any(|m| matches!(m, MavMessage::MISSION_CURRENT(c) if c.seq == 0)));
        assert_eq!(v.target_seq(), Some(0));
        // Set-current brings it back, with a MISSION_CURRENT (a change).
        let back = MavMessage::MISSION_SET_CURRENT(MISSION_SET_CURRENT_DATA {
            seq: 2,
            ..Default::default()
        });
        let out = v.handle(GCS, &back, Instant::now());
        assert!(out
            .iter()
            .any(|m| matches!(m, MavMessage::MISSION_CURRENT(c) if c.seq == 2)));
        assert_eq!(v.target_seq(), Some(2));
    }

    #[test]
    fn px4_profile_starts_the_mission_with_mission_start() {
        let mut v = rover();
        v.set_profile(Profile::Px4);
        upload(&mut v, &[10.0, 20.0, 30.0]);
        assert_eq!(
            command(&mut v, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert_eq!(
            command(&mut v, MavCmd::MAV_CMD_MISSION_START, 2.0, 0.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert_eq!(v.behaviour(), Behaviour::Auto);
        assert_eq!(v.target_seq(), Some(2));
        // Not an ArduPilot command in mavsim.
        let mut a = rover();
        assert_eq!(
            command(&mut a, MavCmd::MAV_CMD_MISSION_START, 0.0, 0.0),
            MavResult::MAV_RESULT_UNSUPPORTED
        );
    }

    #[test]
    fn px4_profile_repositions_then_holds_there() {
        use mavlink::dialects::ardupilotmega::COMMAND_INT_DATA;
        let mut v = rover();
        v.set_profile(Profile::Px4);
        let target = v.frame.to_geo(Ned {
            north: 30.0,
            east: 10.0,
            up: 0.0,
        });
        let reposition = |v: &mut Vehicle, flags: f32| {
            let cmd = COMMAND_INT_DATA {
                command: MavCmd::MAV_CMD_DO_REPOSITION,
                param1: -1.0,
                param2: flags,
                x: (target.lat_deg * 1e7).round() as i32,
                y: (target.lon_deg * 1e7).round() as i32,
                z: f32::NAN,
                ..Default::default()
            };
            let out = v.handle(GCS, &MavMessage::COMMAND_INT(cmd), Instant::now());
            out.iter()
                .find_map(|m| match m {
                    MavMessage::COMMAND_ACK(a) => Some(a.result),
                    _ => None,
                })
                .unwrap()
        };
        // Disarmed: refused for now; armed in MANUAL without the mode flag: refused.
        assert_eq!(
            reposition(&mut v, 1.0),
            MavResult::MAV_RESULT_TEMPORARILY_REJECTED
        );
        assert_eq!(
            command(&mut v, MavCmd::MAV_CMD_COMPONENT_ARM_DISARM, 1.0, 0.0),
            MavResult::MAV_RESULT_ACCEPTED
        );
        assert_eq!(reposition(&mut v, 0.0), MavResult::MAV_RESULT_DENIED);
        assert_eq!(reposition(&mut v, 1.0), MavResult::MAV_RESULT_ACCEPTED);
        assert_eq!(v.behaviour(), Behaviour::Hold);
        assert!(
            matches!(v.heartbeat(), MavMessage::HEARTBEAT(h) if h.custom_mode == 4 << 16 | 3 << 24),
            "AUTO.LOITER"
        );
        run_until(&mut v, 60.0, |v| v.reposition.is_none());
        let here = v.position();
        assert!((here.north - 30.0).abs() < 3.0 && (here.east - 10.0).abs() < 3.0);
        let log = v.take_log();
        assert!(log
            .iter()
            .any(|(_, e)| matches!(e, LogEvent::RepositionReached { .. })));
        // It holds there.
        for _ in 0..500 {
            v.step(0.02);
        }
        assert!(v.position().horizontal_distance(&here) < 1.0);
        // ArduPilot takes a reposition only in GUIDED (a parked rover is in HOLD).
        let mut a = rover();
        assert_eq!(
            command(&mut a, MavCmd::MAV_CMD_DO_REPOSITION, -1.0, 1.0),
            MavResult::MAV_RESULT_FAILED
        );
    }

    #[test]
    fn rally_points_are_refused_not_taken_for_the_mission() {
        use mavlink::dialects::ardupilotmega::{MavMissionResult, MavMissionType};
        let mut v = rover();
        upload(&mut v, &[10.0, 20.0]);
        let out = v.handle(
            GCS,
            &MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
                count: 5,
                mission_type: MavMissionType::MAV_MISSION_TYPE_RALLY,
                ..Default::default()
            }),
            Instant::now(),
        );
        assert!(matches!(out.as_slice(), [MavMessage::MISSION_ACK(a)]
            if a.mavtype == MavMissionResult::MAV_MISSION_UNSUPPORTED
                && a.mission_type == MavMissionType::MAV_MISSION_TYPE_RALLY));
        assert_eq!(v.mission().len(), 3, "the mission is untouched");
    }

    #[test]
    fn generic_profile_keeps_ardupilot_modes_and_px4_missions() {
        let mut v = rover();
        v.set_profile(Profile::Generic);
        match v.heartbeat() {
            MavMessage::HEARTBEAT(h) => {
                assert_eq!(h.autopilot, MavAutopilot::MAV_AUTOPILOT_GENERIC);
                assert_eq!(h.custom_mode, v.mode());
            }
            _ => unreachable!(),
        }
        upload(&mut v, &[10.0, 20.0]);
        start_auto(&mut v);
        assert_eq!(v.target_seq(), Some(0), "item 0 is ordinary");
        assert!(v.telemetry(MISSION_CURRENT_ID).is_some(), "streamed");
    }
}
