//! The simulated autopilot: MAVLink message handling, modes, arming, mission
//! navigation and telemetry, all pure (time is passed in) so it is unit-testable.
//!
//! Navigation follows what 003 §2.5.4 observed of APM:Rover: the vehicle
//! memorises the item it is driving to; a new upload or partial write does not
//! change it, MISSION_SET_CURRENT does; when it is reached the *next index of
//! the mission now on board* becomes the target; after the last item a rover
//! switches to HOLD.

use std::collections::BTreeMap;
use std::time::{Duration, Instant};

use mavlink::dialects::ardupilotmega::{
    MavAutopilot, MavCmd, MavDataStream, MavFrame, MavMessage, MavModeFlag, MavResult, MavSeverity,
    MavState, MavSysStatusSensor, MavType, ATTITUDE_DATA, COMMAND_ACK_DATA, COMMAND_LONG_DATA,
    GLOBAL_POSITION_INT_DATA, HEARTBEAT_DATA, MISSION_CURRENT_DATA, MISSION_ITEM_REACHED_DATA,
    PARAM_VALUE_DATA, STATUSTEXT_DATA, SYS_STATUS_DATA, VFR_HUD_DATA,
};

use crate::kinematics::{Command, GeoPoint, Limits, LocalFrame, Ned, State, VehicleKind};
use crate::log::LogEvent;
use crate::mission::{self, Change, Item, MissionStore};
use crate::modes::{self, Behaviour};
use crate::params::Params;

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
    /// Where a GUIDED take-off climbs to (MAV_CMD_NAV_TAKEOFF).
    takeoff_to: Option<Ned>,
    /// Speed set by DO_CHANGE_SPEED (mission item or command) until the mode changes, m/s.
    speed_override: Option<f64>,
    /// Report no progress: no MISSION_ITEM_REACHED, no "Reached" text, MISSION_CURRENT only
    /// in answer to a set-current (autopilots that leave progress to be inferred).
    quiet_progress: bool,
    sticks: Option<(Sticks, Instant)>,
    sim_time: f64,
    streams: BTreeMap<u32, (Duration, Instant)>,
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
fn is_nav(cmd: MavCmd) -> bool {
    (cmd as u32) < 80 || matches!(cmd, MavCmd::MAV_CMD_NAV_SPLINE_WAYPOINT)
}

fn statustext(severity: MavSeverity, text: &str) -> MavMessage {
    MavMessage::STATUSTEXT(STATUSTEXT_DATA {
        severity,
        text: text.into(),
    })
}

fn command_ack(command: MavCmd, result: MavResult) -> MavMessage {
    MavMessage::COMMAND_ACK(COMMAND_ACK_DATA { command, result })
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
        let params = Params::defaults(cfg.kind, cfg.sysid);
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
            speed_override: None,
            quiet_progress: false,
            sticks: None,
            sim_time: 0.0,
            streams: BTreeMap::new(),
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

    /// Stops (or resumes) reporting mission progress: no MISSION_ITEM_REACHED, no "Reached"
    /// STATUSTEXT, no MISSION_CURRENT stream or change; set-currents are still answered.
    pub fn set_quiet_progress(&mut self, quiet: bool) {
        self.quiet_progress = quiet;
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
                cruise_speed: speed(p("CRUISE_SPEED", 2.0)),
                max_yaw_rate: p("ATC_STR_RAT_MAX", 120.0).max(1.0).to_radians(),
                max_accel: p("ATC_ACCEL_MAX", 2.0).max(0.1),
                max_climb: 0.0,
                loiter_radius: 2.0,
            },
            VehicleKind::Copter => Limits {
                cruise_speed: speed(p("WPNAV_SPEED", 500.0) / 100.0),
                max_yaw_rate: p("ATC_RATE_Y_MAX", 90.0).max(1.0).to_radians(),
                max_accel: (p("WPNAV_ACCEL", 250.0) / 100.0).max(0.1),
                max_climb: (p("WPNAV_SPEED_UP", 250.0) / 100.0).max(0.1),
                loiter_radius: 0.0,
            },
            VehicleKind::Plane => {
                let speed = speed(p("AIRSPEED_CRUISE", 15.0)).max(1.0);
                let bank = p("ROLL_LIMIT_DEG", 45.0).clamp(5.0, 80.0).to_radians();
                Limits {
                    cruise_speed: speed,
                    // Coordinated turn at the bank limit: ω = g·tan(φ)/v.
                    max_yaw_rate: 9.81 * bank.tan() / speed,
                    max_accel: 3.0,
                    max_climb: p("TECS_CLMB_MAX", 5.0).max(0.1),
                    loiter_radius: p("WP_LOITER_RAD", 60.0).max(10.0),
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
        })
    }

    /// Executes a DO_ item the mission passes over.
    fn do_item(&mut self, item: &Item) {
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
        let mut next = seq.max(1);
        while next < count && !is_nav(self.mission.items()[usize::from(next)].command) {
            let item = self.mission.items()[usize::from(next)].clone();
            self.do_item(&item);
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

    fn finish_mission(&mut self, out: &mut Vec<MavMessage>) {
        let last = self.target.map_or(self.current, |t| t.seq);
        self.target = None;
        self.hold_point = self.state.pos;
        out.push(statustext(
            MavSeverity::MAV_SEVERITY_INFO,
            "Mission Complete",
        ));
        self.record(LogEvent::MissionComplete { seq: last });
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
        self.go_to_index(t.seq + 1, "advance", out);
    }

    /// Sets the current mission index (MISSION_SET_CURRENT / DO_SET_MISSION_CURRENT).
    fn set_current(&mut self, seq: u16, out: &mut Vec<MavMessage>) -> bool {
        if seq >= self.mission.count() {
            return false;
        }
        let seq = seq.max(1).min(self.mission.count().saturating_sub(1));
        if seq == 0 {
            return false;
        }
        let driving = self.behaviour() == Behaviour::Auto;
        if seq == self.current && (!driving || self.target_seq() == Some(seq)) {
            // Already there (a ground station resending over a lossy link): nothing changes.
            out.push(self.mission_current());
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
        if self.speed_override.take().is_some() {
            self.record(LogEvent::SpeedChanged { speed: 0.0 });
        }
        self.record(LogEvent::ModeChanged {
            from,
            to: mode,
            name: name.to_owned(),
        });
        if behaviour == Behaviour::Auto {
            let start = if self.current == 0 || self.current >= self.mission.count() {
                1
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
        if !self.armed {
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
                let s = self.sticks.map(|(s, _)| s).unwrap_or_default();
                Command::Sticks {
                    steer: s.steer,
                    throttle: s.throttle,
                }
            }
            Behaviour::Auto => match self.target {
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
            Behaviour::Guided => match self.takeoff_to {
                Some(t) => Command::GoTo(t),
                None => Command::Hold(self.hold_point),
            },
            Behaviour::Hold => Command::Hold(self.hold_point),
        };
        self.state.step(self.cfg.kind, command, &limits, dt);
        if self.behaviour() == Behaviour::Auto {
            if let Some(t) = self.target {
                if self.within(&t.pos, t.radius.unwrap_or_else(|| self.wp_radius())) {
                    self.reached(t, &mut out);
                }
            }
        }
        if let Some(t) = self
            .takeoff_to
            .filter(|_| self.behaviour() == Behaviour::Guided)
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

    /// Within `radius` of `p` (and, for a copter, of its altitude).
    fn within(&self, p: &Ned, radius: f64) -> bool {
        self.state.pos.horizontal_distance(p) <= radius
            && (self.cfg.kind != VehicleKind::Copter || (self.state.pos.up - p.up).abs() <= radius)
    }

    /// Wall-clock duties: heartbeat, telemetry streams, mission request retries,
    /// RC override expiry.
    pub fn poll(&mut self, now: Instant) -> Vec<MavMessage> {
        let mut out = self.mission.poll(now);
        if now >= self.next_heartbeat {
            out.push(self.heartbeat());
            self.next_heartbeat = now + HEARTBEAT_PERIOD;
        }
        if self
            .sticks
            .is_some_and(|(_, at)| now.duration_since(at) > RC_OVERRIDE_TIMEOUT)
        {
            self.sticks = None;
        }
        let due: Vec<u32> = self
            .streams
            .iter_mut()
            .filter(|(_, (_, next))| now >= *next)
            .map(|(id, (period, next))| {
                // Catch up without bursts after a stall.
                *next = (*next + *period).max(now);
                *id
            })
            .collect();
        for id in due {
            if let Some(msg) = self.telemetry(id) {
                out.push(msg);
            }
        }
        out
    }

    fn set_rate(&mut self, id: u32, hz: f64, now: Instant) {
        if hz <= 0.0 || !hz.is_finite() {
            self.streams.remove(&id);
        } else {
            let period = Duration::from_secs_f64(1.0 / hz.min(1000.0));
            self.streams.insert(id, (period, now));
        }
    }

    // ---------------------------------------------------------------- messages out

    /// The HEARTBEAT describing the current mode and arming state.
    pub fn heartbeat(&self) -> MavMessage {
        let mut base = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED;
        match self.behaviour() {
            Behaviour::Manual => base |= MavModeFlag::MAV_MODE_FLAG_MANUAL_INPUT_ENABLED,
            Behaviour::Hold => base |= MavModeFlag::MAV_MODE_FLAG_STABILIZE_ENABLED,
            Behaviour::Auto | Behaviour::Rtl | Behaviour::Guided => {
                base |= MavModeFlag::MAV_MODE_FLAG_STABILIZE_ENABLED
                    | MavModeFlag::MAV_MODE_FLAG_GUIDED_ENABLED
                    | MavModeFlag::MAV_MODE_FLAG_AUTO_ENABLED
            }
        }
        if self.armed {
            base |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
        }
        MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: self.mode,
            mavtype: match self.cfg.kind {
                VehicleKind::Rover => MavType::MAV_TYPE_GROUND_ROVER,
                VehicleKind::Copter => MavType::MAV_TYPE_QUADROTOR,
                VehicleKind::Plane => MavType::MAV_TYPE_FIXED_WING,
            },
            autopilot: MavAutopilot::MAV_AUTOPILOT_ARDUPILOTMEGA,
            base_mode: base,
            system_status: if self.armed {
                MavState::MAV_STATE_ACTIVE
            } else {
                MavState::MAV_STATE_STANDBY
            },
            mavlink_version: 3,
        })
    }

    fn mission_current(&self) -> MavMessage {
        MavMessage::MISSION_CURRENT(MISSION_CURRENT_DATA { seq: self.current })
    }

    fn telemetry(&self, id: u32) -> Option<MavMessage> {
        let time_boot_ms = (self.sim_time * 1000.0) as u32;
        let geo = self.frame.to_geo(self.state.pos);
        let heading_deg = self.state.yaw.to_degrees().rem_euclid(360.0);
        Some(match id {
            GLOBAL_POSITION_INT_ID => MavMessage::GLOBAL_POSITION_INT(GLOBAL_POSITION_INT_DATA {
                time_boot_ms,
                lat: (geo.lat_deg * 1e7).round() as i32,
                lon: (geo.lon_deg * 1e7).round() as i32,
                alt: (geo.alt_m * 1000.0).round() as i32,
                relative_alt: (self.state.pos.up * 1000.0).round() as i32,
                vx: (self.state.vel_north * 100.0).round() as i16,
                vy: (self.state.vel_east * 100.0).round() as i16,
                vz: (-self.state.climb * 100.0).round() as i16,
                hdg: (heading_deg * 100.0).round() as u16 % 36000,
            }),
            ATTITUDE_ID => MavMessage::ATTITUDE(ATTITUDE_DATA {
                time_boot_ms,
                roll: self.state.roll as f32,
                pitch: 0.0,
                yaw: crate::kinematics::wrap_pi(self.state.yaw) as f32,
                rollspeed: 0.0,
                pitchspeed: 0.0,
                yawspeed: self.state.yaw_rate as f32,
            }),
            VFR_HUD_ID => MavMessage::VFR_HUD(VFR_HUD_DATA {
                airspeed: self.state.speed as f32,
                groundspeed: self.state.speed as f32,
                alt: geo.alt_m as f32,
                climb: self.state.climb as f32,
                heading: heading_deg.round() as i16 % 360,
                throttle: if self.armed {
                    (self.state.speed.abs() / self.limits().cruise_speed * 50.0).min(100.0) as u16
                } else {
                    0
                },
            }),
            SYS_STATUS_ID => {
                let sensors = MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_3D_GYRO
                    | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_3D_ACCEL
                    | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_3D_MAG
                    | MavSysStatusSensor::MAV_SYS_STATUS_SENSOR_GPS;
                MavMessage::SYS_STATUS(SYS_STATUS_DATA {
                    onboard_control_sensors_present: sensors,
                    onboard_control_sensors_enabled: sensors,
                    onboard_control_sensors_health: sensors,
                    load: 120,
                    voltage_battery: 12_600,
                    current_battery: if self.armed { 500 } else { 50 },
                    battery_remaining: 100,
                    ..SYS_STATUS_DATA::default()
                })
            }
            MISSION_CURRENT_ID if !self.quiet_progress => self.mission_current(),
            _ => return None,
        })
    }

    fn param_value(&self, index: usize) -> Option<MavMessage> {
        let p = self.params.by_index(index)?;
        Some(MavMessage::PARAM_VALUE(PARAM_VALUE_DATA {
            param_value: p.value,
            param_count: self.params.len() as u16,
            param_index: index as u16,
            param_id: p.name.into(),
            param_type: p.kind,
        }))
    }

    // ---------------------------------------------------------------- messages in

    /// Handles one message from `from` (system, component); returns the replies.
    pub fn handle(&mut self, from: (u8, u8), msg: &MavMessage, now: Instant) -> Vec<MavMessage> {
        let mut out = Vec::new();
        match msg {
            MavMessage::COMMAND_LONG(c) if self.for_us(c.target_system) => {
                let result = self.command(c, now, &mut out);
                out.push(command_ack(c.command, result));
            }
            MavMessage::SET_MODE(m) if self.for_us(m.target_system) => {
                let result = self.change_mode(m.custom_mode, &mut out);
                out.push(command_ack(MavCmd::MAV_CMD_DO_SET_MODE, result));
            }
            MavMessage::REQUEST_DATA_STREAM(r) if self.for_us(r.target_system) => {
                let ids: &[u32] = match r.req_stream_id {
                    MavDataStream::MAV_DATA_STREAM_ALL => &STREAMABLE,
                    MavDataStream::MAV_DATA_STREAM_EXTENDED_STATUS => {
                        &[SYS_STATUS_ID, MISSION_CURRENT_ID]
                    }
                    MavDataStream::MAV_DATA_STREAM_POSITION => &[GLOBAL_POSITION_INT_ID],
                    MavDataStream::MAV_DATA_STREAM_EXTRA1 => &[ATTITUDE_ID],
                    MavDataStream::MAV_DATA_STREAM_EXTRA2 => &[VFR_HUD_ID],
                    _ => &[],
                };
                let hz = if r.start_stop == 0 {
                    0.0
                } else {
                    f64::from(r.req_message_rate)
                };
                for &id in ids {
                    self.set_rate(id, hz, now);
                }
            }
            MavMessage::RC_CHANNELS_OVERRIDE(rc) if self.for_us(rc.target_system) => {
                let prev = self.sticks.map(|(s, _)| s).unwrap_or_default();
                let steer = pwm_to_unit(rc.chan1_raw).unwrap_or(prev.steer);
                let throttle = pwm_to_unit(rc.chan3_raw).unwrap_or(prev.throttle);
                self.sticks = Some((Sticks { steer, throttle }, now));
            }
            MavMessage::PARAM_REQUEST_LIST(r) if self.for_us(r.target_system) => {
                out.extend((0..self.params.len()).filter_map(|i| self.param_value(i)));
            }
            MavMessage::PARAM_REQUEST_READ(r) if self.for_us(r.target_system) => {
                let index = if r.param_index >= 0 {
                    Some(r.param_index as usize)
                } else {
                    r.param_id
                        .to_str()
                        .ok()
                        .and_then(|name| self.params.by_name(name).map(|(i, _)| i))
                };
                out.extend(index.and_then(|i| self.param_value(i)));
            }
            MavMessage::PARAM_SET(s) if self.for_us(s.target_system) => {
                // Unknown names get no answer, as in ArduPilot.
                if let Some(index) = s
                    .param_id
                    .to_str()
                    .ok()
                    .and_then(|n| self.params.set(n, s.param_value))
                {
                    out.extend(self.param_value(index));
                }
            }
            MavMessage::MISSION_COUNT(c) if self.for_us(c.target_system) => {
                out.extend(self.mission.on_count(from, c.count, now));
            }
            MavMessage::MISSION_WRITE_PARTIAL_LIST(p) if self.for_us(p.target_system) => {
                out.extend(
                    self.mission
                        .on_partial(from, p.start_index, p.end_index, now),
                );
            }
            MavMessage::MISSION_ITEM_INT(item) if self.for_us(item.target_system) => {
                self.mission_item(from, item.clone(), now, &mut out);
            }
            MavMessage::MISSION_ITEM(item) if self.for_us(item.target_system) => {
                self.mission_item(from, mission::item_from_float(item), now, &mut out);
            }
            MavMessage::MISSION_REQUEST_LIST(r) if self.for_us(r.target_system) => {
                out.push(self.mission.on_request_list(from));
            }
            MavMessage::MISSION_REQUEST_INT(r) if self.for_us(r.target_system) => {
                out.push(self.mission.on_request(from, r.seq, true));
            }
            MavMessage::MISSION_REQUEST(r) if self.for_us(r.target_system) => {
                out.push(self.mission.on_request(from, r.seq, false));
            }
            MavMessage::MISSION_ACK(a) if self.for_us(a.target_system) => {
                self.mission.on_ack(from);
            }
            MavMessage::MISSION_CLEAR_ALL(c) if self.for_us(c.target_system) => {
                let (replies, change) = self.mission.on_clear(from);
                out.extend(replies);
                self.mission_changed(change);
            }
            MavMessage::MISSION_SET_CURRENT(s) if self.for_us(s.target_system) => {
                let changed = self.set_current(s.seq, &mut out);
                if !changed {
                    // Refused: tell the client what is current instead.
                    out.push(self.mission_current());
                }
            }
            _ => {}
        }
        out
    }

    /// MAV_CMD_NAV_TAKEOFF as a command: as ArduCopter, only armed, in GUIDED, on the ground;
    /// climbs straight up to `alt` metres above home, then holds there.
    fn takeoff(&mut self, alt: f32) -> MavResult {
        if self.cfg.kind != VehicleKind::Copter {
            return MavResult::MAV_RESULT_UNSUPPORTED;
        }
        if !alt.is_finite() || alt <= 0.0 {
            return MavResult::MAV_RESULT_DENIED;
        }
        if !self.armed || self.behaviour() != Behaviour::Guided || self.state.pos.up > 1.0 {
            return MavResult::MAV_RESULT_FAILED;
        }
        self.takeoff_to = Some(Ned {
            up: f64::from(alt),
            ..self.state.pos
        });
        MavResult::MAV_RESULT_ACCEPTED
    }

    fn mission_item(
        &mut self,
        from: (u8, u8),
        item: Item,
        now: Instant,
        out: &mut Vec<MavMessage>,
    ) {
        let (replies, change) = self.mission.on_item(from, item, self.cfg.home, now);
        out.extend(replies);
        if let Some(change) = change {
            self.mission_changed(change);
        }
    }

    /// A committed mission change never moves the memorised target (003 §2.5.4).
    fn mission_changed(&mut self, change: Change) {
        let event = match change {
            Change::Uploaded { count } => LogEvent::MissionUploaded { count },
            Change::PartialWrite { start, end } => LogEvent::MissionPartialWrite { start, end },
            Change::Cleared => LogEvent::MissionCleared,
        };
        self.record(event);
    }

    fn command(
        &mut self,
        c: &COMMAND_LONG_DATA,
        now: Instant,
        out: &mut Vec<MavMessage>,
    ) -> MavResult {
        match c.command {
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM => {
                if c.param1 == 1.0 {
                    self.set_armed(true, out);
                } else if c.param1 == 0.0 {
                    self.set_armed(false, out);
                } else {
                    return MavResult::MAV_RESULT_DENIED;
                }
                MavResult::MAV_RESULT_ACCEPTED
            }
            MavCmd::MAV_CMD_DO_SET_MODE => {
                if c.param2 < 0.0 || !c.param2.is_finite() {
                    return MavResult::MAV_RESULT_DENIED;
                }
                self.change_mode(c.param2 as u32, out)
            }
            MavCmd::MAV_CMD_DO_SET_MISSION_CURRENT => {
                if c.param1 < 0.0 || !c.param1.is_finite() || c.param1 > f32::from(u16::MAX) {
                    return MavResult::MAV_RESULT_DENIED;
                }
                if self.set_current(c.param1 as u16, out) {
                    MavResult::MAV_RESULT_ACCEPTED
                } else {
                    MavResult::MAV_RESULT_DENIED
                }
            }
            MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL => {
                let id = c.param1 as u32;
                if id == 0 {
                    // HEARTBEAT stays at 1 Hz.
                    return MavResult::MAV_RESULT_ACCEPTED;
                }
                if !STREAMABLE.contains(&id) {
                    return MavResult::MAV_RESULT_DENIED;
                }
                let hz = match c.param2 {
                    x if x < 0.0 => 0.0,
                    0.0 => 1.0,
                    us => 1e6 / f64::from(us),
                };
                self.set_rate(id, hz, now);
                MavResult::MAV_RESULT_ACCEPTED
            }
            MavCmd::MAV_CMD_NAV_TAKEOFF => self.takeoff(c.param7),
            MavCmd::MAV_CMD_DO_CHANGE_SPEED => {
                if self.change_speed(c.param2) {
                    MavResult::MAV_RESULT_ACCEPTED
                } else {
                    MavResult::MAV_RESULT_DENIED
                }
            }
            MavCmd::MAV_CMD_REQUEST_MESSAGE => match c.param1 as u32 {
                0 => {
                    out.push(self.heartbeat());
                    MavResult::MAV_RESULT_ACCEPTED
                }
                id => match self.telemetry(id) {
                    Some(m) => {
                        out.push(m);
                        MavResult::MAV_RESULT_ACCEPTED
                    }
                    None => MavResult::MAV_RESULT_UNSUPPORTED,
                },
            },
            _ => MavResult::MAV_RESULT_UNSUPPORTED,
        }
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
    const GCS: (u8, u8) = (255, 190);

    fn rover() -> Vehicle {
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

    fn upload(v: &mut Vehicle, norths: &[f64]) {
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

    fn command(v: &mut Vehicle, command: MavCmd, p1: f32, p2: f32) -> MavResult {
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
    fn command_long(v: &mut Vehicle, cmd: COMMAND_LONG_DATA) -> MavResult {
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
    fn run_until(v: &mut Vehicle, max_s: f64, mut f: impl FnMut(&Vehicle) -> bool) {
        let mut t = 0.0;
        while !f(v) {
            v.step(0.02);
            t += 0.02;
            assert!(t < max_s, "condition not met after {max_s} s");
        }
    }

    fn start_auto(v: &mut Vehicle) {
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

    fn copter() -> Vehicle {
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
}
