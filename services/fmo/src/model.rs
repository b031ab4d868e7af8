//! The station's picture of the fleet, with no I/O: what each vehicle last said and when, the
//! alarms and their acknowledgements, the commands in flight, and the manual-control dead-man.
//!
//! The middleware tasks feed it, the HTTP handlers read [`Station::snapshot`] (the JSON the page
//! renders) and [`Station::manual_tick`] decides what the 20 Hz manual-control loop publishes.
//! Every method takes `now`, so the staleness and dead-man rules are tested without a clock.

use std::collections::{BTreeMap, VecDeque};
use std::time::{Duration, Instant};

use flightplan::api::Progress;
use serde::Serialize;
pub use station_web::CommandStatus;
use station_web::{ms, CommandLog, CommandView};
use usal_types::{
    Alarm, Attitude, AutopilotStatus, Battery, Fence, FlightState, Home, ManualCommand,
    ManualControl, MissionTime, Position, Severity, Speeds, StateChanged,
};

/// Alarms kept per vehicle (oldest dropped first).
const MAX_ALARMS: usize = 50;
/// The browser must repeat its stick input at least this often while the dead-man is held,
/// else the sticks are released (a frozen tab, a closed laptop, a lost Wi-Fi).
pub const MANUAL_INPUT_TIMEOUT: Duration = Duration::from_millis(300);
/// After release, neutral is still published this long so the vehicle hears it over a lossy
/// link; then publishing stops (the VAS releases the sticks on silence anyway).
pub const MANUAL_NEUTRAL_TAIL: Duration = Duration::from_millis(1000);

/// A value with its arrival time.
#[derive(Clone, Debug)]
struct Stamped<T> {
    value: T,
    at: Instant,
}

/// Which `allowed_states` answer the page may offer as buttons.
#[derive(Clone, Debug, Default)]
struct Allowed {
    /// The last answer and the flight state it was computed in.
    states: Option<(Vec<FlightState>, Option<FlightState>, Instant)>,
    /// Why the last call failed, if it did.
    error: Option<String>,
}

/// One alarm as shown.
#[derive(Clone, Debug)]
struct AlarmEntry {
    id: u64,
    alarm: Alarm,
    at: Instant,
    acked: bool,
}

/// A new track point when the vehicle moved at least this far, metres.
const TRACK_STEP_M: f64 = 2.0;
/// Track points kept per vehicle (oldest dropped first).
const MAX_TRACK: usize = 600;

/// How far back the battery's trend is read to estimate the time left.
const BATTERY_TREND: Duration = Duration::from_secs(60);

/// What the station knows of one vehicle (one VAS), keyed by the VAS's item prefix.
#[derive(Clone, Debug, Default)]
struct Vehicle {
    battery: Option<Stamped<Battery>>,
    /// Charge remaining (percent) over the last [`BATTERY_TREND`], oldest first.
    battery_trend: VecDeque<(Instant, f32)>,
    /// The plan's progress, from the vehicle's FPMa.
    plan: Option<Stamped<Progress>>,
    /// The nominal waypoints of the plan its FPMa flies (empty: none loaded).
    route: Vec<flightplan::api::MapPoint>,
    position: Option<Stamped<Position>>,
    /// Where it has been: a point every [`TRACK_STEP_M`], the last [`MAX_TRACK`].
    track: VecDeque<(f64, f64)>,
    /// The autopilot's home.
    home: Option<Stamped<Home>>,
    /// The fence in force on the vehicle (an empty fence: none).
    fence: Option<Stamped<Fence>>,
    /// The health of the vehicle's links, by link name, as its nodes publish it.
    links: BTreeMap<String, Stamped<marea::LinkHealth>>,
    attitude: Option<Stamped<Attitude>>,
    speeds: Option<Stamped<Speeds>>,
    autopilot: Option<Stamped<AutopilotStatus>>,
    flight_state: Option<Stamped<FlightState>>,
    mission_time: Option<Stamped<MissionTime>>,
    last_change: Option<Stamped<StateChanged>>,
    alarms: VecDeque<AlarmEntry>,
    allowed: Allowed,
    heard: Option<Instant>,
    publisher: String,
    /// The variables of the vehicle's other services (a user's own, beside the VAS), by full
    /// name: type name and latest value.
    others: BTreeMap<String, Stamped<(String, serde_json::Value)>>,
}

/// Stick input from the page.
#[derive(Clone, Debug, Default, PartialEq, serde::Deserialize, Serialize)]
pub struct StickInput {
    /// Steering / roll, -1..1, right positive.
    #[serde(default)]
    pub roll: f32,
    /// Pitch, -1..1.
    #[serde(default)]
    pub pitch: f32,
    /// Throttle, -1..1.
    #[serde(default)]
    pub throttle: f32,
    /// Yaw, -1..1.
    #[serde(default)]
    pub yaw: f32,
    /// The dead-man is held: without it every axis is neutral.
    #[serde(default)]
    pub deadman: bool,
    /// `keyboard` or `gamepad`, for display.
    #[serde(default)]
    pub source: String,
}

impl StickInput {
    fn clamped(mut self) -> Self {
        for v in [
            &mut self.roll,
            &mut self.pitch,
            &mut self.throttle,
            &mut self.yaw,
        ] {
            *v = if v.is_finite() {
                v.clamp(-1.0, 1.0)
            } else {
                0.0
            };
        }
        self
    }
}

#[derive(Clone, Debug, Default)]
struct Manual {
    input: StickInput,
    input_at: Option<Instant>,
    released_at: Option<Instant>,
    active: bool,
    /// The vehicle the sticks go to: the commanded one while the dead-man is held, kept after a
    /// release so the neutral tail reaches the vehicle that was driven.
    target: Option<String>,
    /// The commanded vehicle changed while the dead-man was held: it must be released once
    /// before the sticks drive the new one (a held key never jumps from vehicle to vehicle).
    rearm: bool,
    last_sent: Option<(ManualCommand, Instant)>,
    sent: u64,
}

/// The whole station state.
#[derive(Debug)]
pub struct Station {
    vehicles: BTreeMap<String, Vehicle>,
    selected: Option<String>,
    commands: CommandLog,
    next_id: u64,
    manual: Manual,
    stale_after: Duration,
    epoch: Instant,
}

/// One telemetry item as received, for [`Station::update`].
#[derive(Clone, Debug)]
pub enum Item {
    /// `position`.
    Position(Position),
    /// `attitude`.
    Attitude(Attitude),
    /// `speeds`.
    Speeds(Speeds),
    /// `autopilot`.
    Autopilot(AutopilotStatus),
    /// `flight_state`.
    FlightState(FlightState),
    /// `mission_time`.
    MissionTime(MissionTime),
    /// Event `state_changed`.
    StateChanged(StateChanged),
    /// Event `alarm`.
    Alarm(Alarm),
    /// `battery`.
    Battery(Battery),
    /// `home`.
    Home(Home),
    /// `fence`.
    Fence(Fence),
}

/// What the manual-control loop does on one tick.
#[derive(Clone, Debug, PartialEq)]
pub enum ManualTick {
    /// Publish this sample.
    Send(ManualCommand),
    /// Publish nothing.
    Idle,
}

/// A value and its age, as the page gets it.
#[derive(Serialize)]
struct Aged<T> {
    value: T,
    age_ms: u64,
    stale: bool,
}

/// The page's view of everything (`GET /api/state`, and each SSE `state` message).
#[derive(Serialize)]
pub struct Snapshot {
    /// Milliseconds since the station started (to order snapshots).
    pub now_ms: u64,
    /// Values older than this are marked stale.
    pub stale_after_ms: u64,
    /// The vehicle commanded (its VAS prefix).
    pub selected: Option<String>,
    vehicles: Vec<VehicleView>,
    commands: Vec<CommandView>,
    manual: ManualView,
    /// A flight log being played back, if one is heard (set by the station, not the model).
    pub replay: Option<station_web::replay::ReplayView>,
}

#[derive(Serialize)]
struct VehicleView {
    id: String,
    label: String,
    publisher: String,
    link: &'static str,
    heard_ago_ms: Option<u64>,
    flight_state: Option<Aged<FlightState>>,
    autopilot: Option<Aged<AutopilotStatus>>,
    position: Option<Aged<Position>>,
    attitude: Option<Aged<Attitude>>,
    speeds: Option<Aged<Speeds>>,
    mission_time: Option<Aged<MissionTime>>,
    last_change: Option<Aged<StateChanged>>,
    allowed: AllowedView,
    alarms: Vec<AlarmView>,
    unacked_alarms: usize,
    battery: Option<Aged<BatteryView>>,
    plan: Option<Aged<PlanView>>,
    /// The plan's nominal waypoints, in flying order.
    route: Vec<flightplan::api::MapPoint>,
    /// Where it has been, `[lat, lon]`, oldest first.
    track: Vec<(f64, f64)>,
    home: Option<Aged<Home>>,
    /// The fence in force, when it has one.
    fence: Option<Fence>,
    /// Its links as its nodes see them.
    links: Vec<LinkView>,
    /// The variables of its other services, by name.
    services: Vec<OtherItemView>,
}

#[derive(Clone, Serialize)]
struct BatteryView {
    voltage: f32,
    current: Option<f32>,
    remaining: Option<f32>,
    /// Seconds left at the rate the charge fell over the last minute; `None` while it has not
    /// fallen measurably.
    time_left_s: Option<f64>,
}

#[derive(Clone, Serialize)]
struct PlanView {
    name: String,
    leg: Option<String>,
    fraction: f64,
    completed: bool,
    paused: bool,
    /// Seconds to the end of the plan and of the leg (vehicle time).
    eta_s: Option<f64>,
    leg_eta_s: Option<f64>,
}

/// Seconds until `trend`'s last charge reaches zero at the rate it fell since its first
/// sample; `None` while it has not fallen (or over less than five seconds).
fn time_left(trend: &VecDeque<(Instant, f32)>) -> Option<f64> {
    let (t0, r0) = *trend.front()?;
    let (t1, r1) = *trend.back()?;
    let span = t1.saturating_duration_since(t0).as_secs_f64();
    let fell = f64::from(r0 - r1);
    (span >= 5.0 && fell > 0.0).then(|| f64::from(r1) * span / fell)
}

#[derive(Serialize)]
struct LinkView {
    link: String,
    peers: u32,
    /// Smoothed round trip, ms (0: not measured).
    rtt_ms: f32,
    /// Frames received corrupt, fraction, over the last period.
    loss: f32,
    /// Safe messages sent again, fraction, over the last period.
    retransmit_ratio: f32,
    age_ms: u64,
    stale: bool,
}

#[derive(Serialize)]
struct OtherItemView {
    name: String,
    type_name: String,
    value: serde_json::Value,
    age_ms: u64,
    stale: bool,
}

#[derive(Serialize)]
struct AllowedView {
    /// States the VAS accepts now; empty when unknown or outdated.
    states: Vec<FlightState>,
    /// The answer is for the present flight state.
    current: bool,
    age_ms: Option<u64>,
    error: Option<String>,
}

#[derive(Serialize)]
struct AlarmView {
    id: u64,
    severity: Severity,
    text: String,
    age_ms: u64,
    acked: bool,
}

#[derive(Serialize)]
struct ManualView {
    deadman: bool,
    active: bool,
    source: String,
    input: StickInput,
    input_age_ms: Option<u64>,
    sent: u64,
    last_sent: Option<ManualCommand>,
    /// The vehicle the sticks go to (label), if any.
    target: Option<String>,
    /// The dead-man must be released before the sticks drive the newly commanded vehicle.
    rearm: bool,
    /// Vehicles in MANUAL_NAVIGATION (each obeys only the samples addressed to it).
    listening: Vec<String>,
}

/// The vehicle label shown for a VAS prefix: `rover1/vas` → `rover1`, `vas` → `(local)`.
pub fn label_of(prefix: &str) -> String {
    match prefix.strip_suffix("/vas") {
        Some(ns) => ns.to_owned(),
        None if prefix == "vas" => "(no namespace)".to_owned(),
        None => prefix.to_owned(),
    }
}

impl Station {
    /// An empty station marking values stale after `stale_after`.
    pub fn new(stale_after: Duration, now: Instant) -> Self {
        Self {
            vehicles: BTreeMap::new(),
            selected: None,
            commands: CommandLog::default(),
            next_id: 1,
            manual: Manual::default(),
            stale_after,
            epoch: now,
        }
    }

    /// The vehicle commanded.
    pub fn selected(&self) -> Option<&str> {
        self.selected.as_deref()
    }

    /// Chooses the vehicle commanded; unknown prefixes are refused.
    ///
    /// # Errors
    /// The vehicle has not been heard of.
    pub fn select(&mut self, prefix: &str) -> Result<(), String> {
        if !self.vehicles.contains_key(prefix) {
            return Err(format!("unknown vehicle `{prefix}`"));
        }
        if self.selected.as_deref() != Some(prefix) {
            // Sticks never carry over to another vehicle: the one driven gets its neutral tail,
            // the new one nothing until the dead-man is released and held again.
            if self.manual.input.deadman || self.manual.active {
                self.manual.rearm = true;
            }
            self.manual.input.deadman = false;
            self.selected = Some(prefix.to_owned());
        }
        Ok(())
    }

    /// The current flight state of `prefix`, if known.
    pub fn flight_state(&self, prefix: &str) -> Option<FlightState> {
        self.vehicles
            .get(prefix)?
            .flight_state
            .as_ref()
            .map(|s| s.value)
    }

    /// Records an item from the VAS at `prefix` (published by node `publisher`). Returns true
    /// when the flight state changed (the allowed transitions must be asked again).
    pub fn update(&mut self, prefix: &str, publisher: &str, item: Item, now: Instant) -> bool {
        let v = self.vehicles.entry(prefix.to_owned()).or_default();
        v.heard = Some(now);
        publisher.clone_into(&mut v.publisher);
        fn st<T>(value: T, at: Instant) -> Option<Stamped<T>> {
            Some(Stamped { value, at })
        }
        let mut state_changed = false;
        match item {
            Item::Position(p) => {
                let far_enough = v.track.back().is_none_or(|&(lat, lon)| {
                    flightplan::geo::distance(
                        flightplan::geo::GeoPoint::new(lat, lon),
                        flightplan::geo::GeoPoint::new(p.lat, p.lon),
                    ) >= TRACK_STEP_M
                });
                if far_enough && p.lat.is_finite() && p.lon.is_finite() {
                    v.track.push_back((p.lat, p.lon));
                    while v.track.len() > MAX_TRACK {
                        v.track.pop_front();
                    }
                }
                v.position = st(p, now);
            }
            Item::Home(h) => v.home = st(h, now),
            Item::Fence(f) => v.fence = st(f, now),
            Item::Attitude(a) => v.attitude = st(a, now),
            Item::Speeds(s) => v.speeds = st(s, now),
            Item::Autopilot(a) => v.autopilot = st(a, now),
            Item::FlightState(s) => {
                state_changed = v.flight_state.as_ref().map(|x| x.value) != Some(s);
                v.flight_state = st(s, now);
            }
            Item::MissionTime(m) => v.mission_time = st(m, now),
            Item::StateChanged(c) => {
                // The event is reliable and ordered; the `flight_state` variable is best effort
                // and published only on a change, so over a lossy radio its last value may never
                // arrive (the FMo was seen showing CONFIGURE_CHECK long after PARKING).
                state_changed = v.flight_state.as_ref().map(|x| x.value) != Some(c.to);
                v.flight_state = st(c.to, now);
                v.last_change = st(c, now);
            }
            Item::Battery(b) => {
                if let Some(r) = b.remaining {
                    v.battery_trend.push_back((now, r));
                    while v
                        .battery_trend
                        .front()
                        .is_some_and(|(t, _)| now.saturating_duration_since(*t) > BATTERY_TREND)
                    {
                        v.battery_trend.pop_front();
                    }
                }
                v.battery = st(b, now);
            }
            Item::Alarm(alarm) => {
                let id = self.next_id;
                self.next_id += 1;
                v.alarms.push_back(AlarmEntry {
                    id,
                    alarm,
                    at: now,
                    acked: false,
                });
                while v.alarms.len() > MAX_ALARMS {
                    v.alarms.pop_front();
                }
            }
        }
        if self.selected.is_none() {
            self.selected = Some(prefix.to_owned());
        }
        state_changed
    }

    /// Records the plan's progress from the FPMa feeding the VAS at `prefix`. Not an item of
    /// the VAS: it neither makes a vehicle nor says the vehicle's link is up.
    pub fn update_plan(&mut self, prefix: &str, progress: Progress, now: Instant) {
        if let Some(v) = self.vehicles.get_mut(prefix) {
            v.plan = Some(Stamped {
                value: progress,
                at: now,
            });
        }
    }

    /// Records the plan the FPMa feeding the VAS at `prefix` flies, for the map. Ignored for
    /// a vehicle not heard of.
    pub fn update_route(&mut self, prefix: &str, g: &flightplan::api::PlanGeometry) {
        if let Some(v) = self.vehicles.get_mut(prefix) {
            v.route = g.map_points();
        }
    }

    /// Records the health of a link of the vehicle at `prefix` (published by one of its
    /// nodes). Ignored for a vehicle not heard of.
    pub fn update_link(&mut self, prefix: &str, health: marea::LinkHealth, now: Instant) {
        if let Some(v) = self.vehicles.get_mut(prefix) {
            v.links.insert(
                health.link.clone(),
                Stamped {
                    value: health,
                    at: now,
                },
            );
        }
    }

    /// The vehicles heard of (their VAS prefixes).
    pub fn vehicle_ids(&self) -> Vec<String> {
        self.vehicles.keys().cloned().collect()
    }

    /// Records the value of `name`, a variable of another service of the vehicle at `prefix`
    /// (its type's name, and its value as JSON). Ignored for a vehicle not heard of.
    pub fn update_other(
        &mut self,
        prefix: &str,
        name: &str,
        type_name: &str,
        value: serde_json::Value,
        now: Instant,
    ) {
        if let Some(v) = self.vehicles.get_mut(prefix) {
            v.others.insert(
                name.to_owned(),
                Stamped {
                    value: (type_name.to_owned(), value),
                    at: now,
                },
            );
        }
    }

    /// Stores an `allowed_states` answer for `prefix`, asked while it was in `asked_in`.
    pub fn set_allowed(
        &mut self,
        prefix: &str,
        asked_in: Option<FlightState>,
        answer: Result<Vec<FlightState>, String>,
        now: Instant,
    ) {
        let v = self.vehicles.entry(prefix.to_owned()).or_default();
        match answer {
            Ok(states) => {
                v.allowed.states = Some((states, asked_in, now));
                v.allowed.error = None;
            }
            Err(e) => v.allowed.error = Some(e),
        }
    }

    /// Whether `prefix` needs its allowed transitions asked (none yet, outdated, or failed).
    pub fn allowed_outdated(&self, prefix: &str) -> bool {
        let Some(v) = self.vehicles.get(prefix) else {
            return false;
        };
        let current = v.flight_state.as_ref().map(|s| s.value);
        match &v.allowed.states {
            None => true,
            Some((_, asked_in, _)) => *asked_in != current || v.allowed.error.is_some(),
        }
    }

    /// Acknowledges alarm `id` (of any vehicle), or all of `vehicle`'s when `id` is `None`.
    ///
    /// # Errors
    /// No such alarm.
    pub fn ack_alarm(&mut self, vehicle: Option<&str>, id: Option<u64>) -> Result<usize, String> {
        let mut n = 0;
        for (prefix, v) in self.vehicles.iter_mut() {
            if vehicle.is_some_and(|w| w != prefix) {
                continue;
            }
            for a in v.alarms.iter_mut() {
                if id.is_none_or(|id| id == a.id) && !a.acked {
                    a.acked = true;
                    n += 1;
                }
            }
        }
        if n == 0 && id.is_some() {
            return Err("no such unacknowledged alarm".into());
        }
        Ok(n)
    }

    /// Registers a command sent to `vehicle`; returns its id.
    pub fn command_started(&mut self, vehicle: &str, what: &str, now: Instant) -> u64 {
        let id = self.next_id;
        self.next_id += 1;
        self.commands.start(id, vehicle, what.to_owned(), now, ());
        id
    }

    /// Records a command's outcome.
    pub fn command_finished(&mut self, id: u64, outcome: Result<String, String>, now: Instant) {
        self.commands.finish(id, outcome, now);
    }

    /// The status of command `id`.
    pub fn command_status(&self, id: u64) -> Option<(CommandStatus, String)> {
        self.commands
            .get(id)
            .map(|c| (c.status.clone(), c.detail.clone()))
    }

    /// Stick input from the page.
    pub fn manual_input(&mut self, input: StickInput, now: Instant) {
        if !input.deadman {
            self.manual.rearm = false;
        }
        self.manual.input = input.clamped();
        self.manual.input_at = Some(now);
    }

    /// What to publish on this tick of the 20 Hz loop, addressed to the commanded vehicle:
    /// the sticks while the dead-man is held and the page keeps sending; neutral for
    /// [`MANUAL_NEUTRAL_TAIL`] after a release, a silent page or a change of vehicle (to the
    /// vehicle that was driven); nothing otherwise (so an idle station loads no link).
    pub fn manual_tick(&mut self, now: Instant, timestamp_ms: u64) -> ManualTick {
        let m = &mut self.manual;
        let fresh = m
            .input_at
            .is_some_and(|t| now.saturating_duration_since(t) <= MANUAL_INPUT_TIMEOUT);
        let held = m.input.deadman && fresh && !m.rearm && self.selected.is_some();
        let sticks = if held {
            m.active = true;
            m.released_at = None;
            m.target.clone_from(&self.selected);
            ManualControl {
                roll: m.input.roll,
                pitch: m.input.pitch,
                throttle: m.input.throttle,
                yaw: m.input.yaw,
                timestamp_ms,
            }
        } else if m.active {
            // Released by the page or by its silence: neutral for a while, then quiet.
            let released = *m.released_at.get_or_insert(now);
            if now.saturating_duration_since(released) > MANUAL_NEUTRAL_TAIL {
                m.active = false;
                return ManualTick::Idle;
            }
            ManualControl {
                timestamp_ms,
                ..ManualControl::default()
            }
        } else {
            return ManualTick::Idle;
        };
        let Some(target) = m.target.clone() else {
            return ManualTick::Idle;
        };
        let sample = ManualCommand { target, sticks };
        m.sent += 1;
        m.last_sent = Some((sample.clone(), now));
        ManualTick::Send(sample)
    }

    /// The page's view at `now`.
    pub fn snapshot(&self, now: Instant) -> Snapshot {
        let stale = self.stale_after;
        // Items published on change only (flight state, autopilot status) are as fresh as the
        // vehicle's link: they go stale with it.
        let aged = |at: Instant, periodic: bool, link_ok: bool| {
            let age = now.saturating_duration_since(at);
            (ms(age), if periodic { age > stale } else { !link_ok })
        };
        let vehicles = self
            .vehicles
            .iter()
            .map(|(id, v)| {
                let heard = v.heard.map(|h| now.saturating_duration_since(h));
                let link_ok = heard.is_some_and(|h| h <= stale);
                macro_rules! view {
                    ($f:expr, $periodic:expr) => {
                        $f.as_ref().map(|s| {
                            let (age_ms, is_stale) = aged(s.at, $periodic, link_ok);
                            Aged {
                                value: s.value.clone(),
                                age_ms,
                                stale: is_stale,
                            }
                        })
                    };
                }
                let current = v.flight_state.as_ref().map(|s| s.value);
                let (states, is_current, age_ms) = match &v.allowed.states {
                    Some((s, asked_in, at)) => (
                        s.clone(),
                        *asked_in == current,
                        Some(ms(now.saturating_duration_since(*at))),
                    ),
                    None => (Vec::new(), false, None),
                };
                VehicleView {
                    id: id.clone(),
                    label: label_of(id),
                    publisher: v.publisher.clone(),
                    link: match heard {
                        None => "unknown",
                        Some(_) if link_ok => "ok",
                        Some(_) => "stale",
                    },
                    heard_ago_ms: heard.map(ms),
                    flight_state: view!(v.flight_state, false),
                    autopilot: view!(v.autopilot, false),
                    position: view!(v.position, true),
                    attitude: view!(v.attitude, true),
                    speeds: view!(v.speeds, true),
                    mission_time: view!(v.mission_time, true),
                    last_change: view!(v.last_change, false),
                    allowed: AllowedView {
                        states: if is_current { states } else { Vec::new() },
                        current: is_current,
                        age_ms,
                        error: v.allowed.error.clone(),
                    },
                    alarms: v
                        .alarms
                        .iter()
                        .rev()
                        .map(|a| AlarmView {
                            id: a.id,
                            severity: a.alarm.severity,
                            text: a.alarm.text.clone(),
                            age_ms: ms(now.saturating_duration_since(a.at)),
                            acked: a.acked,
                        })
                        .collect(),
                    unacked_alarms: v.alarms.iter().filter(|a| !a.acked).count(),
                    battery: v.battery.as_ref().map(|s| {
                        let (age_ms, stale) = aged(s.at, true, link_ok);
                        Aged {
                            value: BatteryView {
                                voltage: s.value.voltage,
                                current: s.value.current,
                                remaining: s.value.remaining,
                                time_left_s: time_left(&v.battery_trend),
                            },
                            age_ms,
                            stale,
                        }
                    }),
                    plan: v.plan.as_ref().map(|s| {
                        // The FPMa repeats an unchanged progress every 2 s.
                        let (age_ms, _) = aged(s.at, true, true);
                        let stale = age_ms > 3 * ms(stale);
                        let p = &s.value;
                        Aged {
                            value: PlanView {
                                name: p.plan.clone(),
                                leg: p.leg.clone(),
                                fraction: p.fraction,
                                completed: p.completed,
                                paused: p.paused,
                                eta_s: p.eta_s,
                                leg_eta_s: p.leg_eta_s,
                            },
                            age_ms,
                            stale,
                        }
                    }),
                    route: v.route.clone(),
                    track: v.track.iter().copied().collect(),
                    home: view!(v.home, false),
                    fence: v
                        .fence
                        .as_ref()
                        .filter(|f| !f.value.is_empty())
                        .map(|f| f.value.clone()),
                    links: v
                        .links
                        .values()
                        .map(|s| {
                            // Published every second by each node.
                            let (age_ms, stale) = aged(s.at, true, link_ok);
                            LinkView {
                                link: s.value.link.clone(),
                                peers: s.value.peers,
                                rtt_ms: s.value.rtt_ms,
                                loss: s.value.loss,
                                retransmit_ratio: s.value.retransmit_ratio,
                                age_ms,
                                stale,
                            }
                        })
                        .collect(),
                    services: v
                        .others
                        .iter()
                        .map(|(name, s)| {
                            let (age_ms, stale) = aged(s.at, true, link_ok);
                            OtherItemView {
                                name: name.clone(),
                                type_name: s.value.0.clone(),
                                value: s.value.1.clone(),
                                age_ms,
                                stale,
                            }
                        })
                        .collect(),
                }
            })
            .collect();
        let commands = self.commands.view(now, label_of);
        let m = &self.manual;
        Snapshot {
            now_ms: ms(now.saturating_duration_since(self.epoch)),
            stale_after_ms: ms(stale),
            selected: self.selected.clone(),
            vehicles,
            commands,
            replay: None,
            manual: ManualView {
                deadman: m.input.deadman,
                active: m.active,
                source: m.input.source.clone(),
                input: m.input.clone(),
                input_age_ms: m.input_at.map(|t| ms(now.saturating_duration_since(t))),
                sent: m.sent,
                last_sent: m.last_sent.as_ref().map(|(s, _)| s.clone()),
                target: m.target.as_deref().map(label_of),
                rearm: m.rearm,
                listening: self
                    .vehicles
                    .iter()
                    .filter(|(_, v)| {
                        v.flight_state.as_ref().map(|s| s.value)
                            == Some(FlightState::ManualNavigation)
                    })
                    .map(|(id, _)| label_of(id))
                    .collect(),
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn t0() -> Instant {
        Instant::now()
    }

    #[test]
    fn battery_time_left_follows_the_charge_s_fall_and_the_plan_s_eta_its_fpma() {
        let t = t0();
        let mut st = Station::new(Duration::from_secs(2), t);
        let battery = |remaining: f32| {
            Item::Battery(Battery {
                voltage: 12.0,
                current: Some(3.0),
                remaining: Some(remaining),
            })
        };
        // A progress before the vehicle is heard makes no vehicle.
        st.update_plan("rover1/vas", Progress::default(), t);
        assert!(st.vehicle_ids().is_empty());
        st.update("rover1/vas", "air", battery(80.0), t);
        let snap = serde_json::to_value(st.snapshot(t)).unwrap();
        assert_eq!(
            snap["vehicles"][0]["battery"]["value"]["time_left_s"],
            serde_json::Value::Null
        );
        // 2 % in 10 s: 78 % left lasts 390 s.
        st.update(
            "rover1/vas",
            "air",
            battery(78.0),
            t + Duration::from_secs(10),
        );
        let progress = Progress {
            plan: "carpark".into(),
            fraction: 0.5,
            eta_s: Some(95.0),
            ..Progress::default()
        };
        st.update_plan("rover1/vas", progress, t + Duration::from_secs(10));
        let snap = serde_json::to_value(st.snapshot(t + Duration::from_secs(10))).unwrap();
        let v = &snap["vehicles"][0];
        let left = v["battery"]["value"]["time_left_s"].as_f64().unwrap();
        assert!((left - 390.0).abs() < 0.5, "{left}");
        assert_eq!(v["plan"]["value"]["eta_s"], 95.0);
        assert_eq!(v["plan"]["value"]["name"], "carpark");
        // The FPMa's progress does not pass for the VAS's link.
        assert_eq!(v["publisher"], "air");
    }

    #[test]
    fn stale_values_and_link() {
        let t = t0();
        let mut s = Station::new(Duration::from_secs(2), t);
        s.update("rover1/vas", "n", Item::Position(Position::default()), t);
        s.update(
            "rover1/vas",
            "n",
            Item::FlightState(FlightState::Parking),
            t,
        );
        let j = serde_json::to_value(s.snapshot(t + Duration::from_secs(1))).unwrap();
        let v = &j["vehicles"][0];
        assert_eq!(v["label"], "rover1");
        assert_eq!(v["link"], "ok");
        assert_eq!(v["position"]["stale"], false);
        assert_eq!(v["flight_state"]["stale"], false);
        assert_eq!(
            j["selected"], "rover1/vas",
            "first vehicle heard is selected"
        );
        let j = serde_json::to_value(s.snapshot(t + Duration::from_secs(3))).unwrap();
        let v = &j["vehicles"][0];
        assert_eq!(v["link"], "stale");
        assert_eq!(v["position"]["stale"], true);
        assert_eq!(v["flight_state"]["stale"], true, "goes stale with the link");
    }

    #[test]
    fn a_state_change_event_stands_for_a_lost_state_value() {
        let t = t0();
        let mut s = Station::new(Duration::from_secs(2), t);
        s.update(
            "r/vas",
            "n",
            Item::FlightState(FlightState::ConfigureCheck),
            t,
        );
        // The PARKING value was lost on the radio; the reliable event says it.
        let change = StateChanged {
            from: FlightState::ConfigureCheck,
            to: FlightState::Parking,
            cause: "autopilot configured".into(),
        };
        assert!(s.update("r/vas", "n", Item::StateChanged(change.clone()), t));
        assert_eq!(s.flight_state("r/vas"), Some(FlightState::Parking));
        // The value arriving after all changes nothing.
        assert!(!s.update("r/vas", "n", Item::FlightState(FlightState::Parking), t));
        assert!(!s.update("r/vas", "n", Item::StateChanged(change), t));
    }

    #[test]
    fn allowed_states_follow_the_flight_state() {
        let t = t0();
        let mut s = Station::new(Duration::from_secs(2), t);
        assert!(s.update("r/vas", "n", Item::FlightState(FlightState::Parking), t));
        assert!(s.allowed_outdated("r/vas"));
        s.set_allowed(
            "r/vas",
            Some(FlightState::Parking),
            Ok(vec![FlightState::Directed]),
            t,
        );
        assert!(!s.allowed_outdated("r/vas"));
        let j = serde_json::to_value(s.snapshot(t)).unwrap();
        assert_eq!(j["vehicles"][0]["allowed"]["states"][0], "DIRECTED");
        // A new state makes the old answer unusable: no buttons until asked again.
        assert!(!s.update("r/vas", "n", Item::FlightState(FlightState::Parking), t));
        assert!(s.update("r/vas", "n", Item::FlightState(FlightState::Directed), t));
        assert!(s.allowed_outdated("r/vas"));
        let j = serde_json::to_value(s.snapshot(t)).unwrap();
        assert_eq!(j["vehicles"][0]["allowed"]["states"], serde_json::json!([]));
        assert_eq!(j["vehicles"][0]["allowed"]["current"], false);
    }

    #[test]
    fn commands_pending_then_failed_with_reason() {
        let t = t0();
        let mut s = Station::new(Duration::from_secs(2), t);
        let id = s.command_started("r/vas", "change_state MANUAL", t);
        assert_eq!(s.command_status(id).unwrap().0, CommandStatus::Pending);
        s.command_finished(id, Err("link lost".into()), t);
        assert_eq!(
            s.command_status(id),
            Some((CommandStatus::Failed, "link lost".into()))
        );
        for _ in 0..100 {
            let id = s.command_started("r/vas", "x", t);
            s.command_finished(id, Ok(String::new()), t);
        }
        assert!(s.commands.len() <= CommandLog::<()>::KEPT);
    }

    #[test]
    fn alarms_acknowledged() {
        let t = t0();
        let mut s = Station::new(Duration::from_secs(2), t);
        let alarm = |text: &str| {
            Item::Alarm(Alarm {
                severity: Severity::Warning,
                text: text.into(),
            })
        };
        s.update("a/vas", "n", alarm("one"), t);
        s.update("b/vas", "n", alarm("two"), t);
        let j = serde_json::to_value(s.snapshot(t)).unwrap();
        let id = j["vehicles"][0]["alarms"][0]["id"].as_u64().unwrap();
        assert_eq!(s.ack_alarm(None, Some(id)), Ok(1));
        assert!(s.ack_alarm(None, Some(id)).is_err());
        assert_eq!(s.ack_alarm(Some("b/vas"), None), Ok(1));
        let j = serde_json::to_value(s.snapshot(t)).unwrap();
        assert_eq!(j["vehicles"][0]["unacked_alarms"], 0);
        assert_eq!(j["vehicles"][1]["alarms"][0]["acked"], true);
    }

    #[test]
    fn deadman_release_sends_neutral_then_nothing() {
        let t = t0();
        let ms = Duration::from_millis;
        let mut s = Station::new(Duration::from_secs(2), t);
        let held = StickInput {
            throttle: 0.5,
            roll: 7.0, // clamped
            deadman: true,
            ..Default::default()
        };
        s.manual_input(held.clone(), t);
        assert_eq!(
            s.manual_tick(t, 1),
            ManualTick::Idle,
            "no vehicle to address: nothing sent"
        );
        s.update("r/vas", "n", Item::FlightState(FlightState::Parking), t);
        s.manual_input(StickInput::default(), t);
        assert_eq!(s.manual_tick(t, 1), ManualTick::Idle, "idle sends nothing");
        s.manual_input(held.clone(), t);
        let ManualTick::Send(c) = s.manual_tick(t + ms(10), 2) else {
            panic!("held sticks are sent")
        };
        assert_eq!(c.target, "r/vas", "addressed to the commanded vehicle");
        let k = c.sticks;
        assert_eq!((k.throttle, k.roll, k.timestamp_ms), (0.5, 1.0, 2));
        // Stick input without the dead-man is neutral.
        s.manual_input(
            StickInput {
                deadman: false,
                ..held.clone()
            },
            t + ms(50),
        );
        let ManualTick::Send(c) = s.manual_tick(t + ms(60), 3) else {
            panic!("neutral tail")
        };
        assert_eq!((c.target.as_str(), c.sticks.throttle), ("r/vas", 0.0));
        assert_eq!(s.manual_tick(t + ms(2000), 4), ManualTick::Idle);

        // A page that falls silent while holding is released too.
        s.manual_input(held, t + ms(3000));
        assert!(matches!(
            s.manual_tick(t + ms(3100), 5),
            ManualTick::Send(c) if c.sticks.throttle == 0.5
        ));
        let ManualTick::Send(c) = s.manual_tick(t + ms(3500), 6) else {
            panic!("neutral tail after silence")
        };
        assert_eq!(c.sticks.throttle, 0.0);
        assert_eq!(s.manual_tick(t + ms(5000), 7), ManualTick::Idle);
    }

    #[test]
    fn switching_vehicle_releases_the_first_and_rearms_before_the_second() {
        let t = t0();
        let ms = Duration::from_millis;
        let mut s = Station::new(Duration::from_secs(2), t);
        s.update("a/vas", "n", Item::FlightState(FlightState::Parking), t);
        s.update("b/vas", "n", Item::FlightState(FlightState::Parking), t);
        let held = StickInput {
            throttle: 0.5,
            deadman: true,
            ..Default::default()
        };
        s.manual_input(held.clone(), t);
        assert!(matches!(s.manual_tick(t, 1), ManualTick::Send(c) if c.target == "a/vas"));
        assert!(s.select("nope").is_err());
        s.select("b/vas").unwrap();
        assert_eq!(s.selected(), Some("b/vas"));
        assert!(!s.manual.input.deadman);
        // The page keeps posting the held key: the old vehicle gets neutral, the new nothing.
        s.manual_input(held.clone(), t + ms(20));
        let ManualTick::Send(c) = s.manual_tick(t + ms(50), 2) else {
            panic!("neutral tail to the vehicle driven")
        };
        assert_eq!((c.target.as_str(), c.sticks.throttle), ("a/vas", 0.0));
        let j = serde_json::to_value(s.snapshot(t + ms(50))).unwrap();
        assert_eq!(j["manual"]["rearm"], true);
        // Released, then held again: now the new vehicle is driven.
        s.manual_input(StickInput::default(), t + ms(60));
        s.manual_input(held, t + ms(70));
        let ManualTick::Send(c) = s.manual_tick(t + ms(100), 3) else {
            panic!("sticks for the new vehicle")
        };
        assert_eq!((c.target.as_str(), c.sticks.throttle), ("b/vas", 0.5));
    }
}
