//! The executive (FLIGHTPLAN §3.6): a pure state machine that walks a plan with a cursor, keeps
//! the variables, hands out a short look-ahead of waypoints and advances on waypoint-reached
//! reports. No clock, no I/O: the service feeds it and publishes what it returns.
//!
//! The look-ahead is derived from the state each time it is asked for (a simulation on a copy),
//! so a plan has no waypoint limit and a variable set or a command given late still changes what
//! comes next. Every plan change bumps the plan version; waypoints and events carry it and a
//! report for another version is refused, so the vehicle flies one version or the next, never a
//! mix.

use crate::expand::*;
use crate::expr::Value;
use crate::geo::{self, GeoPoint};
use crate::model::*;
use crate::parse::{check_vehicle, modify_node, PlanError};
use crate::vehicle::{VehicleKind, VehicleParams};
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::sync::Arc;
use thiserror::Error;

/// Why a command or report was refused. The executive is unchanged when one is returned.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum CommandError {
    /// The new or modified plan does not validate.
    #[error("invalid plan: {0}")]
    InvalidPlan(#[from] PlanError),
    /// No node has this id.
    #[error("unknown leg `{0}`")]
    UnknownLeg(String),
    /// The plan has no nodes in this stage.
    #[error("the plan has no {0} stage")]
    EmptyStage(Stage),
    /// Neither declared nor a settable built-in.
    #[error("unknown variable `{0}`")]
    UnknownVariable(String),
    /// Value of the wrong type.
    #[error("variable `{name}` is a {expected}")]
    TypeMismatch {
        /// Variable.
        name: String,
        /// Its type.
        expected: crate::expr::ValueType,
    },
    /// The changed plan's nominal expansion would not end (a huge count, circuit number...).
    #[error("{0}")]
    Endless(#[from] ExpandError),
    /// Nothing is being flown.
    #[error("the plan is completed: nothing to skip")]
    NothingToSkip,
    /// `exit_hold` while not holding.
    #[error("the current leg is not a hold")]
    NotHolding,
    /// `pause` twice.
    #[error("already paused")]
    AlreadyPaused,
    /// `resume` while running.
    #[error("not paused")]
    NotPaused,
    /// The command needs a position and none is known yet.
    #[error("no present position is known yet")]
    NoPosition,
    /// A report for another plan version.
    #[error("waypoint of plan version {got}, the current version is {current}")]
    StaleVersion {
        /// Reported.
        got: u64,
        /// Current.
        current: u64,
    },
    /// A report for a waypoint already passed.
    #[error("waypoint {seq} was already reached (next is {next})")]
    AlreadyReached {
        /// Reported.
        seq: u64,
        /// Next expected.
        next: u64,
    },
    /// A report for a waypoint the stream does not reach.
    #[error("waypoint {0} is beyond the end of the plan")]
    BeyondPlan(u64),
    /// No emergency rule has this name.
    #[error("unknown emergency rule `{0}`")]
    UnknownRule(String),
    /// Re-task with no points.
    #[error("re-task needs at least one point")]
    NoPoints,
    /// A command argument out of range (a NaN, a negative length, a latitude of 91...).
    #[error("{what}: {why}")]
    BadArgument {
        /// The argument.
        what: String,
        /// What is expected.
        why: String,
    },
}

fn bad_arg(what: impl Into<String>, why: &str) -> CommandError {
    CommandError::BadArgument {
        what: what.into(),
        why: why.into(),
    }
}

fn check_point(what: &str, p: GeoPoint) -> Result<(), CommandError> {
    if !(p.lat.is_finite() && (-90.0..=90.0).contains(&p.lat)) {
        return Err(bad_arg(
            what,
            &format!("latitude {} is not in -90..90", p.lat),
        ));
    }
    if !(p.lon.is_finite() && (-180.0..=180.0).contains(&p.lon)) {
        return Err(bad_arg(
            what,
            &format!("longitude {} is not in -180..180", p.lon),
        ));
    }
    Ok(())
}

/// An event for stations, tagged with the plan version it belongs to.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Event {
    /// Plan version.
    pub version: u64,
    /// What happened.
    pub kind: EventKind,
}

/// What happened.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "event", rename_all = "kebab-case")]
pub enum EventKind {
    /// A leg became the current one.
    LegStarted {
        /// Leg id.
        leg: String,
    },
    /// A leg ended (`skipped` when by command).
    LegCompleted {
        /// Leg id.
        leg: String,
        /// Ended by a command rather than flown to its end.
        skipped: bool,
    },
    /// A waypoint was reached.
    WaypointReached {
        /// Its sequence number.
        seq: u64,
        /// Its leg.
        leg: String,
    },
    /// A loop finished pass `n` (from 1).
    IterationDone {
        /// Loop id.
        leg: String,
        /// Passes done.
        n: u32,
    },
    /// An alternative chose a branch (0-based; `otherwise` is the last).
    BranchTaken {
        /// Alternative id.
        leg: String,
        /// Branch index.
        branch: usize,
    },
    /// A new stage began.
    StageChanged {
        /// The stage.
        stage: Stage,
    },
    /// Nothing is left to fly.
    PlanCompleted,
    /// Progress by distance (seed 000): flown / (flown + remaining planned).
    Progress {
        /// In [0, 1].
        fraction: f64,
        /// Metres flown in this plan version.
        flown_m: f64,
        /// Metres left in the nominal continuation.
        remaining_m: f64,
    },
    /// A new plan replaced the old one.
    PlanReplaced,
    /// The plan was changed in place (modified or inserted legs).
    PlanModified {
        /// The leg changed or the first inserted.
        leg: String,
    },
    /// An emergency rule fired or the command was given.
    EmergencyFired {
        /// Rule name.
        rule: String,
    },
    /// Paused.
    Paused,
    /// Resumed.
    Resumed,
}

/// Dimensions of a hold commanded in flight at the present position.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HoldHere {
    /// Straight-leg length, metres (default 5 × minimum waypoint distance).
    pub length: Option<f64>,
    /// Width, metres (default as for plan holds).
    pub width: Option<f64>,
    /// Turn direction.
    pub turn: Turn,
    /// Inbound course; default the present track.
    pub inbound_course: Option<f64>,
    /// Shape; default rectangle for a rover, racetrack otherwise.
    pub shape: Option<HoldShape>,
}

impl Default for HoldHere {
    fn default() -> Self {
        Self {
            length: None,
            width: None,
            turn: Turn::R,
            inbound_course: None,
            shape: None,
        }
    }
}

/// When re-tasked points are visited.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RetaskMode {
    /// Interrupt the current leg, visit the points, then resume the leg where it was.
    Now,
    /// Insert the points as TF legs after the current leg (a new plan version).
    AfterCurrentLeg,
}

/// Telemetry the executive reads for built-in variables and the present position.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Telemetry {
    /// Present position.
    pub position: Option<GeoPoint>,
    /// Altitude (`alt`).
    pub alt: Option<f64>,
    /// Ground speed (`ground_speed`).
    pub ground_speed: Option<f64>,
    /// Battery (`battery`), percent.
    pub battery: Option<f64>,
    /// Seconds since start (`elapsed_s`).
    pub elapsed_s: Option<f64>,
}

/// A snapshot of the executive for stations.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExecState {
    /// Plan version.
    pub version: u64,
    /// Plan name.
    pub plan: String,
    /// Current stage.
    pub stage: Option<Stage>,
    /// Current leg id.
    pub leg: Option<String>,
    /// Sequence number of the next waypoint.
    pub next_seq: u64,
    /// Paused.
    pub paused: bool,
    /// Completed.
    pub completed: bool,
    /// The current leg is a hold.
    pub holding: bool,
    /// Enclosing loops: (id, passes done).
    pub loops: Vec<(String, u32)>,
    /// Variables.
    pub vars: BTreeMap<String, Value>,
}

#[derive(Clone, Debug)]
struct Frame {
    index: usize,
    kind: FrameKind,
}

#[derive(Clone, Debug)]
enum FrameKind {
    Stage(Stage),
    Loop {
        iteration: u32,
        produced: bool,
        waits: bool,
    },
    Branch(usize),
}

#[derive(Clone, Debug)]
struct HoldState {
    hold: Hold,
    entered: bool,
    circuits: u32,
    exit: bool,
    waits: bool,
}

#[derive(Clone, Debug)]
struct Active {
    id: String,
    wps: Vec<Waypoint>,
    next: usize,
    hold: Option<HoldState>,
    /// A hold-here or re-task that returns to the suspended leg when done.
    interrupt: bool,
}

/// The run-time executive. See the module docs.
#[derive(Clone, Debug)]
pub struct Executive {
    plan: Arc<FlightPlan>,
    vehicle: VehicleParams,
    version: u64,
    vars: BTreeMap<String, Value>,
    frames: Vec<Frame>,
    active: Option<Active>,
    suspended: Option<Active>,
    next_seq: u64,
    last: Option<Origin>,
    present: Option<GeoPoint>,
    /// The altitude telemetry last reported (an HA hold ends on it, not on its own waypoints'
    /// altitude, which the `alt` variable takes as each waypoint is reached).
    measured_alt: Option<f64>,
    paused: bool,
    completed: bool,
    nominal: bool,
    simulating: bool,
    flown: f64,
    rule_state: Vec<bool>,
    events: Vec<Event>,
}

/// Steps a simulation takes before giving up on a plan that does not end.
const SIM_LIMIT: usize = 1_000_000;

/// Why a nominal expansion failed.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum ExpandError {
    /// The plan did not end within the step limit.
    #[error("the plan produces more than {0} waypoints without ending")]
    Endless(usize),
}

/// The number of waypoints [`expand_nominal`] gives, without keeping them: a plan is flown
/// only if this ends, so a mistyped count cannot make every look-ahead and progress computation
/// walk a million waypoints.
///
/// # Errors
/// [`ExpandError::Endless`] for a plan that does not end within the limit.
pub fn nominal_len(plan: FlightPlan, vehicle: VehicleParams) -> Result<usize, ExpandError> {
    let mut ex = Executive::new(plan, vehicle);
    ex.nominal = true;
    ex.simulating = true;
    ex.settle();
    let mut n = 0;
    while ex.head().is_some() {
        if n >= SIM_LIMIT {
            return Err(ExpandError::Endless(SIM_LIMIT));
        }
        n += 1;
        ex.reach_head();
    }
    Ok(n)
}

/// The waypoint stream the executive produces with no in-flight changes: holds and loops that
/// wait for a command or a condition are flown once and their waypoints marked `waits`.
///
/// # Errors
/// [`ExpandError::Endless`] for a plan that does not end.
pub fn expand_nominal(
    plan: FlightPlan,
    vehicle: VehicleParams,
) -> Result<Vec<Waypoint>, ExpandError> {
    let mut ex = Executive::new(plan, vehicle);
    ex.nominal = true;
    ex.simulating = true;
    ex.settle();
    let mut out = Vec::new();
    while let Some(w) = ex.head().cloned() {
        if out.len() >= SIM_LIMIT {
            return Err(ExpandError::Endless(SIM_LIMIT));
        }
        let mut w = w;
        w.seq = ex.next_seq;
        w.version = ex.version;
        out.push(w);
        ex.reach_head();
    }
    Ok(out)
}

impl Executive {
    /// An executive at the start of `plan` (version 1). The plan is assumed validated for
    /// `vehicle` (as [`crate::parse::parse_plan`] does).
    pub fn new(plan: FlightPlan, vehicle: VehicleParams) -> Self {
        let mut ex = Self {
            plan: Arc::new(plan),
            vehicle,
            version: 1,
            vars: BTreeMap::new(),
            frames: Vec::new(),
            active: None,
            suspended: None,
            next_seq: 0,
            last: None,
            present: None,
            measured_alt: None,
            paused: false,
            completed: false,
            nominal: false,
            simulating: false,
            flown: 0.0,
            rule_state: Vec::new(),
            events: Vec::new(),
        };
        ex.start();
        ex
    }

    fn start(&mut self) {
        for b in ["alt", "ground_speed", "elapsed_s"] {
            self.vars.entry(b.to_string()).or_insert(Value::Number(0.0));
        }
        self.vars
            .entry("battery".into())
            .or_insert(Value::Number(100.0));
        for v in &self.plan.variables {
            self.vars.insert(v.name.clone(), v.init);
        }
        self.frames.clear();
        self.active = None;
        self.suspended = None;
        self.completed = false;
        self.flown = 0.0;
        match Stage::ALL
            .into_iter()
            .find(|s| !self.plan.stage(*s).is_empty())
        {
            Some(s) => {
                self.frames.push(Frame {
                    index: 0,
                    kind: FrameKind::Stage(s),
                });
                self.emit(EventKind::StageChanged { stage: s });
            }
            None => self.finish(),
        }
        self.rule_state = self
            .plan
            .emergencies
            .iter()
            .map(|r| r.on.holds(&|n| self.var(n)))
            .collect();
        self.settle();
    }

    // ----- queries -------------------------------------------------------------------------

    /// The current plan version (starts at 1, increases with every plan change).
    pub fn version(&self) -> u64 {
        self.version
    }

    /// The plan being flown.
    pub fn plan(&self) -> &FlightPlan {
        &self.plan
    }

    /// The next `n` waypoints, each with its sequence number and the plan version; empty when
    /// paused or completed. Computed from the present state, so it reflects every change.
    pub fn next_waypoints(&self, n: usize) -> Vec<Waypoint> {
        if self.paused || self.completed {
            return Vec::new();
        }
        let mut sim = self.sim_copy();
        // `n` may be far more than the plan holds: grow as waypoints come.
        let mut out = Vec::with_capacity(n.min(64));
        for k in 0..n {
            let Some(w) = sim.head() else { break };
            let mut w = w.clone();
            w.seq = self.next_seq + k as u64;
            w.version = self.version;
            out.push(w);
            sim.reach_head();
        }
        out
    }

    /// Events since the last call, oldest first.
    pub fn take_events(&mut self) -> Vec<Event> {
        std::mem::take(&mut self.events)
    }

    /// A snapshot for stations.
    pub fn state(&self) -> ExecState {
        let mut loops = Vec::new();
        self.walk_frames(|node, kind| {
            if let FrameKind::Loop { iteration, .. } = kind {
                loops.push((node.id.clone(), *iteration));
            }
        });
        ExecState {
            version: self.version,
            plan: self.plan.name.clone(),
            stage: self.stage(),
            leg: self.active.as_ref().map(|a| a.id.clone()),
            next_seq: self.next_seq,
            paused: self.paused,
            completed: self.completed,
            holding: self.active.as_ref().is_some_and(|a| a.hold.is_some()),
            loops,
            vars: self.vars.clone(),
        }
    }

    /// Progress by distance: flown / (flown + remaining nominal distance), 1 when completed.
    pub fn progress(&self) -> f64 {
        let (flown, remaining) = self.distances();
        if self.completed {
            return 1.0;
        }
        if flown + remaining <= 0.0 {
            return 0.0;
        }
        flown / (flown + remaining)
    }

    /// Metres flown in this plan version and metres left in the nominal continuation (what
    /// [`Self::progress`] divides).
    pub fn distances_m(&self) -> (f64, f64) {
        self.distances()
    }

    /// Numbers the waypoints from `seq` on, when that is above the next sequence number. A
    /// service calls it after handing waypoints to a queue it cannot take back (the VAS keeps
    /// driving to its target after "clear"), so a late report for one of them is not taken
    /// for the new waypoint with the same number. Nothing else changes.
    pub fn skip_seqs_to(&mut self, seq: u64) {
        self.next_seq = self.next_seq.max(seq);
    }

    fn distances(&self) -> (f64, f64) {
        let mut sim = self.sim_copy();
        sim.nominal = true;
        sim.paused = false;
        let start = sim.flown;
        let mut steps = 0;
        while sim.head().is_some() && steps < SIM_LIMIT {
            sim.reach_head();
            steps += 1;
        }
        (self.flown, sim.flown - start)
    }

    fn stage(&self) -> Option<Stage> {
        match self.frames.first().map(|f| &f.kind) {
            Some(FrameKind::Stage(s)) => Some(*s),
            _ => None,
        }
    }

    // ----- inputs from the vehicle ----------------------------------------------------------

    /// The vehicle reached waypoint `seq` of plan `version`. Reaching a later waypoint than the
    /// next one passes the ones before.
    ///
    /// # Errors
    /// A stale version, a waypoint already reached, or one beyond the end of the plan.
    pub fn waypoint_reached(&mut self, version: u64, seq: u64) -> Result<(), CommandError> {
        if version != self.version {
            return Err(CommandError::StaleVersion {
                got: version,
                current: self.version,
            });
        }
        if seq < self.next_seq {
            return Err(CommandError::AlreadyReached {
                seq,
                next: self.next_seq,
            });
        }
        // Check first so a refused report changes nothing.
        let ahead = usize::try_from(seq - self.next_seq).unwrap_or(usize::MAX);
        if ahead >= SIM_LIMIT || self.sim_copy().skip_heads(ahead + 1) <= ahead {
            return Err(CommandError::BeyondPlan(seq));
        }
        for _ in 0..=ahead {
            self.reach_head();
        }
        self.emit_progress();
        self.check_rules();
        Ok(())
    }

    /// Telemetry: present position and built-in variables. Emergency rules are checked.
    /// Values that are not finite numbers (and positions off the globe) are ignored.
    pub fn update_telemetry(&mut self, t: Telemetry) {
        if let Some(p) = t.position.filter(|p| check_point("position", *p).is_ok()) {
            self.present = Some(p);
        }
        for (name, v) in [
            ("alt", t.alt),
            ("ground_speed", t.ground_speed),
            ("battery", t.battery),
            ("elapsed_s", t.elapsed_s),
        ] {
            if let Some(v) = v.filter(|v| v.is_finite()) {
                if name == "alt" {
                    self.measured_alt = Some(v);
                }
                self.vars.insert(name.into(), Value::Number(v));
            }
        }
        self.check_rules();
    }

    // ----- commands -------------------------------------------------------------------------

    /// Replaces the whole plan, atomically: it is validated first, then the old one is dropped
    /// and the new one starts from its first stage with a new version. Returns the version.
    ///
    /// # Errors
    /// [`CommandError::InvalidPlan`] when the plan does not suit the vehicle.
    pub fn replace_plan(&mut self, plan: FlightPlan) -> Result<u64, CommandError> {
        check_vehicle(&plan, &self.vehicle)?;
        nominal_len(plan.clone(), self.vehicle.clone())?;
        if let Some(a) = self.active.take() {
            self.emit(EventKind::LegCompleted {
                leg: a.id,
                skipped: true,
            });
        }
        self.plan = Arc::new(plan);
        self.version += 1;
        self.emit(EventKind::PlanReplaced);
        self.start();
        Ok(self.version)
    }

    /// Changes attributes of leg `id` (e.g. a scan's `spacing`, a hold's `length`), validated as
    /// the parser would. A leg being flown restarts from the present position with the new
    /// parameters (a hold keeps its circuit count). Returns the new version.
    ///
    /// # Errors
    /// Unknown leg, or the modified leg does not validate.
    pub fn modify_leg(
        &mut self,
        id: &str,
        changes: &[(String, String)],
    ) -> Result<u64, CommandError> {
        let node = self
            .plan
            .find(id)
            .ok_or_else(|| CommandError::UnknownLeg(id.into()))?;
        let new = modify_node(node, changes, &self.plan, &self.vehicle)?;
        let mut changed = (*self.plan).clone();
        if let Some(slot) = node_mut(&mut changed, id) {
            *slot = new;
        }
        nominal_len(changed.clone(), self.vehicle.clone())?;
        self.plan = Arc::new(changed);
        self.version += 1;
        self.emit(EventKind::PlanModified { leg: id.into() });
        let current = self
            .active
            .as_ref()
            .is_some_and(|a| a.id == id && !a.interrupt);
        if current {
            let circuits = self
                .active
                .as_ref()
                .and_then(|a| a.hold.as_ref())
                .map(|h| h.circuits);
            self.active = None;
            self.settle();
            if let (Some(c), Some(h)) =
                (circuits, self.active.as_mut().and_then(|a| a.hold.as_mut()))
            {
                h.circuits = c;
            }
        }
        Ok(self.version)
    }

    /// Ends the current leg now and continues with the next one.
    ///
    /// # Errors
    /// [`CommandError::NothingToSkip`] when the plan is completed.
    pub fn skip_leg(&mut self) -> Result<(), CommandError> {
        let Some(a) = self.active.take() else {
            return Err(CommandError::NothingToSkip);
        };
        self.emit(EventKind::LegCompleted {
            leg: a.id.clone(),
            skipped: true,
        });
        if a.interrupt {
            self.active = self.suspended.take();
        } else if let Some(f) = self.frames.last_mut() {
            f.index += 1;
        }
        self.settle();
        Ok(())
    }

    /// Continues with node `id` (a leg, or a loop / alternative, which is entered afresh).
    ///
    /// # Errors
    /// [`CommandError::UnknownLeg`].
    pub fn goto_leg(&mut self, id: &str) -> Result<(), CommandError> {
        let frames = path_to(&self.plan, id).ok_or_else(|| CommandError::UnknownLeg(id.into()))?;
        self.jump(frames);
        Ok(())
    }

    /// Continues with the first node of `stage`.
    ///
    /// # Errors
    /// [`CommandError::EmptyStage`] when the plan has no such stage.
    pub fn goto_stage(&mut self, stage: Stage) -> Result<(), CommandError> {
        if self.plan.stage(stage).is_empty() {
            return Err(CommandError::EmptyStage(stage));
        }
        self.jump(vec![Frame {
            index: 0,
            kind: FrameKind::Stage(stage),
        }]);
        Ok(())
    }

    /// Sets a plan variable (or the built-ins `alt`, `ground_speed`, `battery`, `elapsed_s`).
    /// Conditions see it from now on; emergency rules are checked.
    ///
    /// # Errors
    /// Unknown variable or wrong type.
    pub fn set_var(&mut self, name: &str, value: Value) -> Result<(), CommandError> {
        let ty = match self.plan.var_type(name) {
            Some(_) if name == "iteration" => {
                return Err(CommandError::UnknownVariable(name.into()))
            }
            Some(t) => t,
            None => return Err(CommandError::UnknownVariable(name.into())),
        };
        if value.ty() != ty {
            return Err(CommandError::TypeMismatch {
                name: name.into(),
                expected: ty,
            });
        }
        if let Value::Number(n) = value {
            if !n.is_finite() {
                return Err(bad_arg(name, "must be a finite number"));
            }
            if name == "alt" {
                self.measured_alt = Some(n);
            }
        }
        self.vars.insert(name.into(), value);
        self.check_rules();
        Ok(())
    }

    /// Interrupts the current leg with a hold (HM) at the present position; `exit_hold` (or
    /// `skip_leg`) resumes the interrupted leg where it was.
    ///
    /// # Errors
    /// [`CommandError::NoPosition`] before any position is known.
    /// Lengths, widths and courses out of range are refused as [`CommandError::BadArgument`].
    pub fn hold_here(&mut self, p: &HoldHere) -> Result<(), CommandError> {
        let min = self.vehicle.min_wp_distance;
        for (what, v) in [("length", p.length), ("width", p.width)] {
            if let Some(v) = v {
                if !v.is_finite() || v < min {
                    return Err(bad_arg(
                        format!("hold {what} {v}"),
                        &format!("must be at least the minimum waypoint distance, {min} m"),
                    ));
                }
            }
        }
        let shape = p
            .shape
            .unwrap_or(if self.vehicle.kind == VehicleKind::Rover {
                HoldShape::Rectangle
            } else {
                HoldShape::Racetrack
            });
        if let Some(w) = p.width {
            let turn = 2.0 * self.vehicle.turn_radius;
            if shape == HoldShape::Racetrack && w < turn {
                return Err(bad_arg(
                    format!("hold width {w}"),
                    &format!("is below the vehicle's turn limit of {turn} m"),
                ));
            }
        }
        if let Some(c) = p.inbound_course.filter(|c| !c.is_finite()) {
            return Err(bad_arg(
                format!("inbound course {c}"),
                "must be a number of degrees",
            ));
        }
        let pos = self
            .present
            .or(self.last.map(|o| o.pos))
            .ok_or(CommandError::NoPosition)?;
        let course = p
            .inbound_course
            .unwrap_or_else(|| match (self.last, self.head()) {
                (Some(l), Some(h)) if geo::distance(l.pos, h.pos()) > 0.1 => {
                    geo::inverse(l.pos, h.pos()).azi1
                }
                _ => 0.0,
            });
        let hold = Hold {
            kind: HoldKind::HM,
            fix: Fix {
                id: "here".into(),
                pos,
                alt: self.last.map(|o| o.alt),
            },
            inbound_course: course,
            turn: p.turn,
            length: Some(p.length.unwrap_or(5.0 * self.vehicle.min_wp_distance)),
            time: None,
            width: p.width,
            shape,
            circuits: None,
            until: None,
            target_alt: None,
            alt_tolerance: 5.0,
            common: LegCommon::default(),
        };
        let id = format!("hold-here.{}", self.next_seq);
        let act = Active {
            id: id.clone(),
            wps: Vec::new(),
            next: 0,
            hold: Some(HoldState {
                hold,
                entered: false,
                circuits: 0,
                exit: false,
                waits: true,
            }),
            interrupt: true,
        };
        self.interrupt_with(act);
        // The vehicle is at the fix: the entry crossing is now.
        self.hold_crossing();
        self.settle();
        Ok(())
    }

    /// Ends the current hold: at its next fix crossing, or at once with `now`.
    ///
    /// # Errors
    /// [`CommandError::NotHolding`].
    pub fn exit_hold(&mut self, now: bool) -> Result<(), CommandError> {
        let a = self.active.as_mut().ok_or(CommandError::NotHolding)?;
        let h = a.hold.as_mut().ok_or(CommandError::NotHolding)?;
        h.exit = true;
        if now {
            return self.skip_leg();
        }
        Ok(())
    }

    /// Stops handing out waypoints (the look-ahead is empty) until `resume`.
    ///
    /// # Errors
    /// [`CommandError::AlreadyPaused`].
    pub fn pause(&mut self) -> Result<(), CommandError> {
        if self.paused {
            return Err(CommandError::AlreadyPaused);
        }
        self.paused = true;
        self.emit(EventKind::Paused);
        Ok(())
    }

    /// Resumes where the plan was paused.
    ///
    /// # Errors
    /// [`CommandError::NotPaused`].
    pub fn resume(&mut self) -> Result<(), CommandError> {
        if !self.paused {
            return Err(CommandError::NotPaused);
        }
        self.paused = false;
        self.emit(EventKind::Resumed);
        Ok(())
    }

    /// Re-tasks the vehicle to points of interest, visited in nearest-neighbour order (seed 002)
    /// from the present position (`Now`) or from the end of the current leg (`AfterCurrentLeg`),
    /// at `alt` (default the present altitude). Returns the plan version.
    ///
    /// # Errors
    /// No points, or no position known.
    pub fn retask(
        &mut self,
        points: &[GeoPoint],
        alt: Option<f64>,
        mode: RetaskMode,
    ) -> Result<u64, CommandError> {
        if points.is_empty() {
            return Err(CommandError::NoPoints);
        }
        for (k, p) in points.iter().enumerate() {
            check_point(&format!("point {}", k + 1), *p)?;
        }
        if let Some(a) = alt.filter(|a| !a.is_finite()) {
            return Err(bad_arg(
                format!("altitude {a}"),
                "must be a number of metres",
            ));
        }
        let here = self.present.or(self.last.map(|o| o.pos));
        // Points visited after the current leg are ordered from where that leg ends.
        let from = match mode {
            RetaskMode::Now => here,
            RetaskMode::AfterCurrentLeg => self
                .active
                .as_ref()
                .and_then(|a| a.wps.last())
                .map(Waypoint::pos)
                .or(here),
        }
        .ok_or(CommandError::NoPosition)?;
        let order = nearest_neighbour(from, points);
        let alt = alt.or(self.last.map(|o| o.alt));
        match mode {
            RetaskMode::Now => {
                let id = format!("retask.{}", self.next_seq);
                let ctx = self.ctx();
                let wps: Vec<Waypoint> = order
                    .iter()
                    .flat_map(|p| {
                        let leg = PathLeg {
                            kind: PathKind::TF,
                            fix: Fix {
                                id: "poi".into(),
                                pos: *p,
                                alt,
                            },
                            course: None,
                            length: None,
                            center: None,
                            turn: None,
                            common: LegCommon {
                                fly_over: Some(true),
                                ..LegCommon::default()
                            },
                        };
                        expand_path(&leg, &id, &ctx)
                    })
                    .collect();
                let wps = enforce_min_distance(Some(from), wps, self.vehicle.min_wp_distance);
                self.interrupt_with(Active {
                    id,
                    wps,
                    next: 0,
                    hold: None,
                    interrupt: true,
                });
                self.settle();
            }
            RetaskMode::AfterCurrentLeg => {
                let base = format!("retask.v{}", self.version + 1);
                let nodes: Vec<Node> = order
                    .iter()
                    .enumerate()
                    .map(|(k, p)| Node {
                        id: format!("{base}.{}", k + 1),
                        line: 0,
                        col: 0,
                        kind: NodeKind::Path(PathLeg {
                            kind: PathKind::TF,
                            fix: Fix {
                                id: format!("poi{}", k + 1),
                                pos: *p,
                                alt,
                            },
                            course: None,
                            length: None,
                            center: None,
                            turn: None,
                            common: LegCommon {
                                fly_over: Some(true),
                                ..LegCommon::default()
                            },
                        }),
                        source: None,
                    })
                    .collect();
                self.insert_after_current(nodes)?;
            }
        }
        Ok(self.version)
    }

    /// Inserts legs written in the plan's XML (`<leg .../>`, `<scan>`, `<iterative>`...) right
    /// after the current leg: a new plan version. They may use the plan's fixes and variables;
    /// those without an `id` are named `insert.v<version>.<n>`. Returns the version.
    ///
    /// # Errors
    /// [`CommandError::InvalidPlan`] naming the line of the fragment that is wrong (an unknown
    /// fix, an id already used...), or [`CommandError::NothingToSkip`] when the plan is completed.
    pub fn insert_legs(&mut self, xml: &str) -> Result<u64, CommandError> {
        if self.frames.is_empty() {
            return Err(CommandError::NothingToSkip);
        }
        let prefix = format!("insert.v{}", self.version + 1);
        let nodes = crate::parse::parse_fragment(xml, &self.plan, &self.vehicle, &prefix)?;
        if nodes.is_empty() {
            return Err(bad_arg("legs", "the fragment has no legs"));
        }
        self.insert_after_current(nodes)
    }

    /// Inserts nodes right after the current leg (a new plan version). Returns the version.
    ///
    /// # Errors
    /// [`CommandError::NothingToSkip`] when the plan is completed.
    pub fn insert_after_current(&mut self, nodes: Vec<Node>) -> Result<u64, CommandError> {
        if self.frames.is_empty() {
            return Err(CommandError::NothingToSkip);
        }
        let first = nodes.first().map(|n| n.id.clone()).unwrap_or_default();
        let frames = self.frames.clone();
        let mut changed = (*self.plan).clone();
        let Some(list) = list_mut(&mut changed, &frames) else {
            return Err(CommandError::NothingToSkip);
        };
        let at = frames.last().map_or(0, |f| f.index + 1).min(list.len());
        for (k, n) in nodes.into_iter().enumerate() {
            list.insert(at + k, n);
        }
        nominal_len(changed.clone(), self.vehicle.clone())?;
        self.plan = Arc::new(changed);
        self.version += 1;
        self.emit(EventKind::PlanModified { leg: first });
        self.settle();
        Ok(self.version)
    }

    /// Fires emergency rule `name`, or with `None` the default reaction: the approach stage,
    /// else landing, else a hold here.
    ///
    /// # Errors
    /// Unknown rule, or the reaction cannot apply.
    pub fn emergency(&mut self, name: Option<&str>) -> Result<(), CommandError> {
        let (rule, action) = match name {
            Some(n) => {
                let r = self
                    .plan
                    .emergencies
                    .iter()
                    .find(|r| r.name == n)
                    .ok_or_else(|| CommandError::UnknownRule(n.into()))?;
                (r.name.clone(), r.action.clone())
            }
            None => ("default".to_string(), EmergencyAction::Land),
        };
        self.emit(EventKind::EmergencyFired { rule });
        self.apply(&action)
    }

    // ----- internals ------------------------------------------------------------------------

    fn apply(&mut self, action: &EmergencyAction) -> Result<(), CommandError> {
        match action {
            EmergencyAction::GotoStage { stage } => self.goto_stage(*stage),
            EmergencyAction::GotoLeg { leg } => self.goto_leg(leg),
            EmergencyAction::Hold => self.hold_here(&HoldHere::default()),
            EmergencyAction::Land => {
                if !self.plan.approach.is_empty() && self.stage() < Some(Stage::Approach) {
                    self.goto_stage(Stage::Approach)
                } else if !self.plan.landing.is_empty() {
                    self.goto_stage(Stage::Landing)
                } else {
                    self.hold_here(&HoldHere::default())
                }
            }
        }
    }

    fn check_rules(&mut self) {
        let mut fire = None;
        for i in 0..self.plan.emergencies.len() {
            let now = self.plan.emergencies[i].on.holds(&|n| self.var(n));
            let was = self.rule_state.get(i).copied().unwrap_or(false);
            if let Some(s) = self.rule_state.get_mut(i) {
                *s = now;
            }
            if now && !was && fire.is_none() {
                fire = Some(i);
            }
        }
        if let Some(i) = fire {
            let rule = self.plan.emergencies[i].clone();
            self.emit(EventKind::EmergencyFired { rule: rule.name });
            // A reaction that cannot apply (e.g. a hold with no position yet) leaves the plan as
            // it is; the event still tells stations the rule fired.
            let _ = self.apply(&rule.action);
        }
    }

    fn var(&self, name: &str) -> Option<Value> {
        if name == "iteration" {
            let it = self.frames.iter().rev().find_map(|f| match f.kind {
                FrameKind::Loop { iteration, .. } => Some(iteration),
                _ => None,
            });
            return Some(Value::Number(f64::from(it.unwrap_or(0))));
        }
        self.vars.get(name).copied()
    }

    fn holds(&self, c: &crate::expr::Condition) -> bool {
        c.holds(&|n| self.var(n))
    }

    fn emit(&mut self, kind: EventKind) {
        if !self.simulating {
            self.events.push(Event {
                version: self.version,
                kind,
            });
        }
    }

    fn emit_progress(&mut self) {
        let (flown, remaining) = self.distances();
        let fraction = if self.completed || flown + remaining <= 0.0 {
            if self.completed {
                1.0
            } else {
                0.0
            }
        } else {
            flown / (flown + remaining)
        };
        self.emit(EventKind::Progress {
            fraction,
            flown_m: flown,
            remaining_m: remaining,
        });
    }

    fn sim_copy(&self) -> Executive {
        let mut sim = Executive {
            events: Vec::new(),
            ..self.clone()
        };
        sim.simulating = true;
        sim
    }

    /// Reaches up to `n` heads; returns how many there were.
    fn skip_heads(&mut self, n: usize) -> usize {
        let mut k = 0;
        while k < n && self.head().is_some() {
            self.reach_head();
            k += 1;
        }
        k
    }

    fn head(&self) -> Option<&Waypoint> {
        self.active.as_ref().and_then(|a| a.wps.get(a.next))
    }

    fn ctx(&self) -> Ctx<'_> {
        Ctx {
            vehicle: &self.vehicle,
            prev: self.last,
            plan_speed: self.plan.default_speed,
        }
    }

    fn finish(&mut self) {
        if !self.completed {
            self.completed = true;
            self.frames.clear();
            self.emit(EventKind::PlanCompleted);
        }
    }

    fn interrupt_with(&mut self, act: Active) {
        self.emit(EventKind::LegStarted {
            leg: act.id.clone(),
        });
        let old = self.active.take();
        match old {
            Some(o) if o.interrupt => {
                self.emit(EventKind::LegCompleted {
                    leg: o.id,
                    skipped: true,
                });
            }
            Some(o) => self.suspended = Some(o),
            None => {}
        }
        if self.completed {
            // A hold commanded after the end: fly it, then end again.
            self.completed = false;
        }
        self.active = Some(act);
    }

    fn jump(&mut self, frames: Vec<Frame>) {
        if let Some(a) = self.active.take() {
            self.emit(EventKind::LegCompleted {
                leg: a.id,
                skipped: true,
            });
        }
        self.suspended = None;
        let old = self.stage();
        self.frames = frames;
        self.completed = false;
        if let Some(s) = self.stage() {
            if Some(s) != old {
                self.emit(EventKind::StageChanged { stage: s });
            }
        }
        // Entering a branch by a jump counts as taking it.
        let mut taken = Vec::new();
        self.walk_frames(|node, kind| {
            if let FrameKind::Branch(b) = kind {
                taken.push((node.id.clone(), *b));
            }
        });
        for (leg, branch) in taken {
            self.emit(EventKind::BranchTaken { leg, branch });
        }
        self.settle();
    }

    /// Calls `f` with each construct node on the cursor path and its frame.
    fn walk_frames(&self, mut f: impl FnMut(&Node, &FrameKind)) {
        let Some(FrameKind::Stage(s)) = self.frames.first().map(|f| &f.kind) else {
            return;
        };
        let mut list: &[Node] = self.plan.stage(*s);
        for w in self.frames.windows(2) {
            let Some(node) = list.get(w[0].index) else {
                return;
            };
            f(node, &w[1].kind);
            list = match child_list(node, &w[1].kind) {
                Some(l) => l,
                None => return,
            };
        }
    }

    /// Brings the state to one where `head()` is the next waypoint, or the plan is completed.
    fn settle(&mut self) {
        let plan = Arc::clone(&self.plan);
        for _ in 0..SIM_LIMIT {
            if self.completed {
                return;
            }
            if let Some(a) = &self.active {
                if a.next < a.wps.len() {
                    return;
                }
                let Some(a) = self.active.take() else { return };
                self.emit(EventKind::LegCompleted {
                    leg: a.id.clone(),
                    skipped: false,
                });
                if a.interrupt {
                    self.active = self.suspended.take();
                } else if let Some(f) = self.frames.last_mut() {
                    f.index += 1;
                }
                continue;
            }
            let Some(top) = self.frames.last().cloned() else {
                self.finish();
                return;
            };
            let list = list_of(&plan, &self.frames);
            let Some(node) = list.get(top.index) else {
                self.end_of_list(&plan);
                continue;
            };
            match &node.kind {
                NodeKind::Iterative(it) => {
                    if let LoopMode::While(c) = &it.mode {
                        // `iteration` reads 0 before the first pass.
                        self.frames.push(Frame {
                            index: 0,
                            kind: FrameKind::Loop {
                                iteration: 0,
                                produced: false,
                                waits: false,
                            },
                        });
                        let go = self.holds(c);
                        self.frames.pop();
                        if !go {
                            self.bump();
                            continue;
                        }
                    }
                    let waits = self.loop_waits(&it.mode);
                    self.frames.push(Frame {
                        index: 0,
                        kind: FrameKind::Loop {
                            iteration: 0,
                            produced: false,
                            waits,
                        },
                    });
                }
                NodeKind::Alternative(alt) => {
                    let chosen = alt
                        .branches
                        .iter()
                        .position(|b| b.cond.as_ref().is_none_or(|c| self.holds(c)));
                    match chosen {
                        Some(b) => {
                            self.emit(EventKind::BranchTaken {
                                leg: node.id.clone(),
                                branch: b,
                            });
                            self.frames.push(Frame {
                                index: 0,
                                kind: FrameKind::Branch(b),
                            });
                        }
                        None => self.bump(),
                    }
                }
                _ => self.activate(node),
            }
        }
        // A plan that loops without producing anything: stop rather than spin.
        self.finish();
    }

    fn bump(&mut self) {
        if let Some(f) = self.frames.last_mut() {
            f.index += 1;
        }
    }

    /// In a nominal run, a loop whose condition only plan variables decide would repeat forever
    /// (nothing changes them): it is flown once and marked.
    fn loop_waits(&self, mode: &LoopMode) -> bool {
        let decided_by_vars = |c: &crate::expr::Condition| !c.expr.mentions("iteration");
        match mode {
            LoopMode::Count(_) => false,
            LoopMode::While(c) => decided_by_vars(c) && self.holds(c),
            LoopMode::Until(c) => decided_by_vars(c) && !self.holds(c),
        }
    }

    fn end_of_list(&mut self, plan: &FlightPlan) {
        let Some(f) = self.frames.pop() else { return };
        match f.kind {
            FrameKind::Stage(s) => {
                let next = Stage::ALL
                    .into_iter()
                    .filter(|x| *x > s)
                    .find(|x| !plan.stage(*x).is_empty());
                match next {
                    Some(n) => {
                        self.frames.push(Frame {
                            index: 0,
                            kind: FrameKind::Stage(n),
                        });
                        self.emit(EventKind::StageChanged { stage: n });
                    }
                    None => self.finish(),
                }
            }
            FrameKind::Loop {
                iteration,
                produced,
                waits,
            } => {
                let n = iteration + 1;
                let list = list_of(plan, &self.frames);
                let Some(node) = self.frames.last().and_then(|p| list.get(p.index)) else {
                    return;
                };
                self.emit(EventKind::IterationDone {
                    leg: node.id.clone(),
                    n,
                });
                let NodeKind::Iterative(it) = &node.kind else {
                    return;
                };
                self.frames.push(Frame {
                    index: 0,
                    kind: FrameKind::Loop {
                        iteration: n,
                        produced: false,
                        waits,
                    },
                });
                let again = produced
                    && !(self.nominal && waits)
                    && match &it.mode {
                        LoopMode::Count(c) => n < *c,
                        LoopMode::While(c) => self.holds(c),
                        LoopMode::Until(c) => !self.holds(c),
                    };
                if !again {
                    self.frames.pop();
                    self.bump();
                }
            }
            FrameKind::Branch(_) => self.bump(),
        }
    }

    fn activate(&mut self, node: &Node) {
        let ctx = self.ctx();
        let id = node.id.as_str();
        let mut hold = None;
        let wps = match &node.kind {
            NodeKind::Path(l) => expand_path(l, id, &ctx),
            NodeKind::Hold(h) => {
                // An HM waits for its condition or a command, an HA for its altitude: a nominal
                // run shows one circuit of either, marked.
                let waits = h.circuits.is_none()
                    && match h.kind {
                        HoldKind::HM => !h.until.as_ref().is_some_and(|c| self.holds(c)),
                        HoldKind::HA => true,
                        HoldKind::HF => false,
                    };
                hold = Some(HoldState {
                    hold: h.clone(),
                    entered: false,
                    circuits: 0,
                    exit: false,
                    waits,
                });
                hold_entry(h, id, &ctx)
            }
            NodeKind::Scan(s) => expand_scan(s, id, &ctx),
            NodeKind::Perimeter(p) => expand_perimeter(p, id, &ctx),
            NodeKind::Takeoff(t) => expand_takeoff(t, id, &ctx),
            NodeKind::Landing(l) => expand_landing(l, id, &ctx),
            NodeKind::Iterative(_) | NodeKind::Alternative(_) => Vec::new(),
        };
        let mut wps =
            enforce_min_distance(self.last.map(|o| o.pos), wps, self.vehicle.min_wp_distance);
        let waits = self.in_waiting_loop() || hold.as_ref().is_some_and(|h| h.waits);
        for w in &mut wps {
            w.waits = waits;
        }
        self.emit(EventKind::LegStarted {
            leg: node.id.clone(),
        });
        let at_fix = hold.is_some() && wps.is_empty();
        self.active = Some(Active {
            id: node.id.clone(),
            wps,
            next: 0,
            hold,
            interrupt: false,
        });
        if at_fix {
            self.hold_crossing();
        }
        self.mark_produced();
    }

    fn in_waiting_loop(&self) -> bool {
        self.frames
            .iter()
            .any(|f| matches!(f.kind, FrameKind::Loop { waits: true, .. }))
    }

    fn mark_produced(&mut self) {
        if self.active.as_ref().is_some_and(|a| a.next < a.wps.len()) {
            for f in &mut self.frames {
                if let FrameKind::Loop { produced, .. } = &mut f.kind {
                    *produced = true;
                }
            }
        }
    }

    /// At a hold's fix: decide whether to exit, else append the next circuit.
    fn hold_crossing(&mut self) {
        let nominal = self.nominal;
        // A nominal run assumes the altitude is reached during the first circuit.
        let alt = match (nominal, self.measured_alt, self.var("alt")) {
            (false, Some(a), _) => Some(a),
            (_, _, Some(Value::Number(a))) => Some(a),
            _ => None,
        };
        let until = self
            .active
            .as_ref()
            .and_then(|a| a.hold.as_ref())
            .and_then(|h| h.hold.until.clone())
            .is_some_and(|c| self.holds(&c));
        let ctx_last = self.last;
        let plan_speed = self.plan.default_speed;
        let vehicle = self.vehicle.clone();
        let in_loop_wait = self.in_waiting_loop();
        let Some(a) = self.active.as_mut() else {
            return;
        };
        let Some(hs) = a.hold.as_mut() else { return };
        if hs.entered {
            hs.circuits += 1;
        } else {
            hs.entered = true;
        }
        let h = &hs.hold;
        let ctx = Ctx {
            vehicle: &vehicle,
            prev: ctx_last,
            plan_speed,
        };
        let limit = h.circuits.is_some_and(|c| hs.circuits >= c);
        let done = hs.exit
            || match h.kind {
                HoldKind::HF => hs.circuits >= h.circuits.unwrap_or(1),
                HoldKind::HA => {
                    let target = hold_alt(h, &ctx);
                    let reached =
                        nominal || alt.is_some_and(|a| (a - target).abs() <= h.alt_tolerance);
                    limit || (hs.circuits >= 1 && reached)
                }
                HoldKind::HM => limit || until || (nominal && hs.waits && hs.circuits >= 1),
            };
        if done {
            // Drop anything not yet flown: the leg ends here.
            a.wps.truncate(a.next);
            return;
        }
        let mut circuit = hold_circuit(h, &a.id, &ctx);
        let waits = hs.waits || in_loop_wait;
        for w in &mut circuit {
            w.waits = waits;
        }
        let prev = a
            .wps
            .get(a.next.wrapping_sub(1))
            .map(Waypoint::pos)
            .or(ctx_last.map(|o| o.pos));
        let circuit = enforce_min_distance(prev, circuit, vehicle.min_wp_distance);
        a.wps.truncate(a.next);
        a.wps.extend(circuit);
    }

    fn reach_head(&mut self) {
        let Some(a) = self.active.as_mut() else {
            return;
        };
        let Some(w) = a.wps.get(a.next).cloned() else {
            return;
        };
        a.next += 1;
        if let Some(l) = self.last {
            self.flown += geo::distance(l.pos, w.pos());
        }
        self.last = Some(Origin {
            pos: w.pos(),
            alt: w.alt,
            speed: w.speed,
        });
        self.present = None;
        self.vars.insert("alt".into(), Value::Number(w.alt));
        self.emit(EventKind::WaypointReached {
            seq: self.next_seq,
            leg: w.leg.clone(),
        });
        self.next_seq += 1;
        if w.fix_crossing {
            self.hold_crossing();
        }
        self.settle();
    }
}

fn child_list<'a>(node: &'a Node, kind: &FrameKind) -> Option<&'a [Node]> {
    match (&node.kind, kind) {
        (NodeKind::Iterative(it), FrameKind::Loop { .. }) => Some(&it.body),
        (NodeKind::Alternative(a), FrameKind::Branch(b)) => {
            a.branches.get(*b).map(|br| br.body.as_slice())
        }
        _ => None,
    }
}

/// The node list the innermost frame indexes.
fn list_of<'a>(plan: &'a FlightPlan, frames: &[Frame]) -> &'a [Node] {
    let Some(FrameKind::Stage(s)) = frames.first().map(|f| &f.kind) else {
        return &[];
    };
    let mut list: &[Node] = plan.stage(*s);
    for w in frames.windows(2) {
        list = match list.get(w[0].index).and_then(|n| child_list(n, &w[1].kind)) {
            Some(l) => l,
            None => return &[],
        };
    }
    list
}

/// The node list the innermost frame indexes, mutable; `None` if the cursor does not match the
/// plan (it always does: the cursor is built over this plan and only leaves are replaced).
fn list_mut<'a>(plan: &'a mut FlightPlan, frames: &[Frame]) -> Option<&'a mut Vec<Node>> {
    let Some(FrameKind::Stage(stage)) = frames.first().map(|f| &f.kind) else {
        return None;
    };
    let mut list = plan.stage_mut(*stage);
    for w in frames.windows(2) {
        let node = list.get_mut(w[0].index)?;
        list = match (&mut node.kind, &w[1].kind) {
            (NodeKind::Iterative(it), FrameKind::Loop { .. }) => &mut it.body,
            (NodeKind::Alternative(a), FrameKind::Branch(b)) => &mut a.branches.get_mut(*b)?.body,
            _ => return None,
        };
    }
    Some(list)
}

fn node_mut<'a>(plan: &'a mut FlightPlan, id: &str) -> Option<&'a mut Node> {
    fn walk<'a>(nodes: &'a mut [Node], id: &str) -> Option<&'a mut Node> {
        for n in nodes.iter_mut() {
            if n.id == id {
                return Some(n);
            }
            let found = match &mut n.kind {
                NodeKind::Iterative(it) => walk(&mut it.body, id),
                NodeKind::Alternative(a) => {
                    a.branches.iter_mut().find_map(|b| walk(&mut b.body, id))
                }
                _ => None,
            };
            if found.is_some() {
                return found;
            }
        }
        None
    }
    let FlightPlan {
        takeoff,
        departure,
        mission,
        approach,
        landing,
        ..
    } = plan;
    [takeoff, departure, mission, approach, landing]
        .into_iter()
        .find_map(|l| walk(l, id))
}

/// The cursor that points at node `id`.
fn path_to(plan: &FlightPlan, id: &str) -> Option<Vec<Frame>> {
    fn search(list: &[Node], id: &str, frames: &mut Vec<Frame>) -> bool {
        for (i, n) in list.iter().enumerate() {
            if let Some(f) = frames.last_mut() {
                f.index = i;
            }
            if n.id == id {
                return true;
            }
            match &n.kind {
                NodeKind::Iterative(it) => {
                    frames.push(Frame {
                        index: 0,
                        kind: FrameKind::Loop {
                            iteration: 0,
                            produced: false,
                            waits: false,
                        },
                    });
                    if search(&it.body, id, frames) {
                        return true;
                    }
                    frames.pop();
                }
                NodeKind::Alternative(a) => {
                    for (b, br) in a.branches.iter().enumerate() {
                        frames.push(Frame {
                            index: 0,
                            kind: FrameKind::Branch(b),
                        });
                        if search(&br.body, id, frames) {
                            return true;
                        }
                        frames.pop();
                    }
                }
                _ => {}
            }
        }
        false
    }
    for s in Stage::ALL {
        let mut frames = vec![Frame {
            index: 0,
            kind: FrameKind::Stage(s),
        }];
        if search(plan.stage(s), id, &mut frames) {
            return Some(frames);
        }
    }
    None
}

/// Orders points by repeatedly going to the nearest unvisited one (seed 002's "Nearest
/// Neighbor": not optimal, but fast and predictable).
pub fn nearest_neighbour(from: GeoPoint, points: &[GeoPoint]) -> Vec<GeoPoint> {
    let mut left: Vec<GeoPoint> = points.to_vec();
    let mut cur = from;
    let mut out = Vec::with_capacity(left.len());
    while !left.is_empty() {
        let (i, _) = left
            .iter()
            .enumerate()
            .map(|(i, p)| (i, geo::distance(cur, *p)))
            .fold(
                (0, f64::INFINITY),
                |best, x| if x.1 < best.1 { x } else { best },
            );
        cur = left.remove(i);
        out.push(cur);
    }
    out
}
