//! The service's core: one executive and the VAS waypoint queue it feeds, driven by plans,
//! commands, waypoint-reached reports and telemetry. The middleware stays outside: the VAS is
//! reached through [`VasPort`], and what stations should see is collected for the caller to
//! publish, so the core runs the same against the real VAS or a test double.
//!
//! Feeding: the VAS should hold the executive's next `lookahead` waypoints. After every input
//! the core compares what it handed out (`pending`) with the executive's look-ahead; when the
//! look-ahead merely extends it, only the new waypoints are pushed; otherwise (a command, a
//! late variable change, a new version) the VAS queue is cleared ("a new queue follows",
//! 003 §6.2.2) and refilled. The VAS keeps driving to its current target through a clear, so
//! unless that target is still the executive's next waypoint, the new waypoints are numbered
//! past everything handed out before, and the report of the abandoned target is ignored.
//!
//! The flight state is the operator's (pilot in command): the core never asks the
//! VAS for one. A loaded plan fills the queue and waits; [`Readiness`] (variable `ready`)
//! tells stations "plan ready, press Start" until the operator puts the vehicle in
//! WAYPOINT_NAVIGATION.
//!
//! One file of ~1,000 lines on purpose: about 530 are the core, one state machine whose feeding
//! rule above is read as a whole; the rest are its tests and their VAS double, at the bottom of
//! the file they test.

use std::collections::VecDeque;
use std::time::Instant;

use async_trait::async_trait;
use flightplan::eta::EtaEstimator;
use usal_types::{AltRef, Battery, FlightState, Position, QueueStatus, WaypointKind};

use flightplan::api::{
    CommandAck, PlanEvent, PlanEventKind, PlanGeometry, PlanLoaded, PlanState, Progress, Readiness,
};
use flightplan::check::CheckedPlan;
use flightplan::exec::{Executive, HoldHere, RetaskMode, Telemetry};
use flightplan::expand::{Waypoint, WaypointTag};
use flightplan::expr::Value;
use flightplan::geo::GeoPoint;
use flightplan::model::Stage;
use flightplan::vehicle::VehicleParams;

/// What the core needs of the VAS (`<vas>/push_waypoints`, `clear_waypoints`): no state
/// change, which is the operator's. Errors are the reason as text, as the middleware's
/// functions give it.
#[async_trait]
pub trait VasPort: Send + Sync {
    /// Appends waypoints (after a clear: replaces what follows the target).
    async fn push(&self, wps: Vec<usal_types::Waypoint>) -> Result<QueueStatus, String>;
    /// "A new queue follows".
    async fn clear(&self) -> Result<QueueStatus, String>;
    /// Hands the plan's fence to the VAS (`None`: the plan has none, the vehicle's own fence
    /// alone stays in force). The default does nothing (a VAS that checks no fence).
    async fn set_fence(&self, fence: Option<usal_types::Fence>) -> Result<String, FenceRefusal> {
        let _ = fence;
        Ok("no fence on this VAS".into())
    }
}

/// Why a plan's fence is not at the VAS.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum FenceRefusal {
    /// The VAS refused it (not a fence, or wider than the vehicle's): the plan cannot fly.
    Refused(String),
    /// The VAS did not answer: it checks the vehicle's own fence alone meanwhile.
    Unreachable(String),
}

impl std::fmt::Display for FenceRefusal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Refused(why) | Self::Unreachable(why) => f.write_str(why),
        }
    }
}

/// Settings of the core.
#[derive(Clone, Debug)]
pub struct CoreConfig {
    /// Vehicle parameters plans are validated and expanded for.
    pub vehicle: VehicleParams,
    /// Waypoints the VAS should hold ahead of the vehicle.
    pub lookahead: usize,
}

/// An in-flight command (the service's functions, one variant each).
#[derive(Clone, Debug, PartialEq)]
pub enum Command {
    /// `skip_leg`.
    SkipLeg,
    /// `goto_leg`.
    GotoLeg(String),
    /// `goto_stage`.
    GotoStage(Stage),
    /// `set_var`.
    SetVar(String, Value),
    /// `hold_here`.
    HoldHere(HoldHere),
    /// `exit_hold` (`true`: at once, else at the next fix crossing).
    ExitHold(bool),
    /// `pause`.
    Pause,
    /// `resume`.
    Resume,
    /// `modify_leg`.
    ModifyLeg(String, Vec<(String, String)>),
    /// `retask`.
    Retask(Vec<GeoPoint>, Option<f64>, RetaskMode),
    /// `insert_legs`: legs in the plan's XML, flown after the current one.
    InsertLegs(String),
    /// `emergency` (a rule name, or the default reaction).
    Emergency(Option<String>),
}

/// What the caller should publish after an input.
#[derive(Clone, Debug, Default)]
pub struct Outputs {
    /// Events, oldest first.
    pub events: Vec<PlanEvent>,
    /// The new progress, when it changed.
    pub progress: Option<Progress>,
    /// The new state, when it changed.
    pub state: Option<PlanState>,
    /// The plan's geometry, when the plan changed (a new version).
    pub geometry: Option<PlanGeometry>,
    /// Whether the plan waits for the operator's start, when that changed.
    pub readiness: Option<Readiness>,
}

/// The service's core. See the module docs.
pub struct Core<V> {
    cfg: CoreConfig,
    vas: V,
    exec: Option<Executive>,
    /// Waypoints the VAS holds that belong to the executive's present look-ahead, target
    /// first, with the plan version they were handed out under.
    pending: VecDeque<(u64, usal_types::Waypoint)>,
    /// Highest sequence number ever handed to the VAS.
    max_pushed: Option<u64>,
    /// The VAS queue must be cleared before the next push (a failed call left it unknown).
    must_flush: bool,
    /// A call to the VAS failed: [`Core::sync`] should be retried.
    dirty: bool,
    vas_state: Option<FlightState>,
    /// The readiness last handed out for publishing.
    readiness: Option<Readiness>,
    last_reached: Option<u64>,
    started: Option<Instant>,
    /// The speed flown, for the ETAs in the progress.
    eta: EtaEstimator,
    /// Where the plan came from (`source` of [`Core::load`]).
    source: String,
    /// The geometry of the plan version being flown (version 0 before any plan).
    geometry: PlanGeometry,
    out: Outputs,
    /// Counts the inputs that may have changed what [`Core::snapshot`] returns.
    changes: u64,
    /// Another ground station wrote the autopilot's mission (who, and how many items): nothing
    /// is handed to the VAS until the operator resumes the plan.
    taken_over: Option<String>,
}

/// What the core keeps across a restart of the service: the executive (plan, cursor,
/// variables, version, sequence numbers) and what the VAS was handed, so a restarted FPMa goes
/// on where it was instead of flying the plan again from its start.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct Persisted {
    /// Where the plan came from.
    pub source: String,
    /// The executive.
    pub exec: Executive,
    /// Waypoints handed to the VAS and not reached yet, with their plan version.
    pub pending: Vec<(u64, usal_types::Waypoint)>,
    /// Highest sequence number ever handed to the VAS.
    pub max_pushed: Option<u64>,
    /// The last waypoint reached.
    pub last_reached: Option<u64>,
    /// Another ground station's mission flies (who, how many items): a restarted FPMa still
    /// leaves it alone until the operator resumes the plan.
    #[serde(default)]
    pub taken_over: Option<String>,
}

fn to_vas(w: &Waypoint, alt_ref: AltRef) -> usal_types::Waypoint {
    usal_types::Waypoint {
        seq: w.seq,
        lat: w.lat,
        lon: w.lon,
        alt: w.alt,
        speed: w.speed,
        fly_over: w.fly_over,
        leg: w.leg.clone(),
        kind: match w.tag {
            WaypointTag::Nav => WaypointKind::Nav,
            WaypointTag::Takeoff => WaypointKind::Takeoff,
            WaypointTag::Land => WaypointKind::Land,
        },
        alt_ref,
        land_start: w.land_start,
    }
}

impl<V: VasPort> Core<V> {
    /// A core with no plan yet.
    pub fn new(cfg: CoreConfig, vas: V) -> Self {
        Self {
            cfg,
            vas,
            exec: None,
            pending: VecDeque::new(),
            max_pushed: None,
            must_flush: false,
            dirty: false,
            vas_state: None,
            readiness: None,
            last_reached: None,
            started: None,
            eta: EtaEstimator::new(),
            source: String::new(),
            geometry: PlanGeometry::default(),
            out: Outputs::default(),
            changes: 0,
            taken_over: None,
        }
    }

    /// Grows whenever something [`Core::snapshot`] returns may have changed.
    pub fn changes(&self) -> u64 {
        self.changes
    }

    /// The state to persist; `None` before any plan.
    pub fn snapshot(&self) -> Option<Persisted> {
        Some(Persisted {
            source: self.source.clone(),
            exec: self.exec.clone()?,
            pending: self.pending.iter().cloned().collect(),
            max_pushed: self.max_pushed,
            last_reached: self.last_reached,
            taken_over: self.taken_over.clone(),
        })
    }

    /// Goes on from a persisted state (after a restart): the plan and its position are taken
    /// as they were; the VAS queue, which may have moved on meanwhile, is cleared and refilled
    /// ("a new queue follows"), first accounting for a waypoint it reports reached. The
    /// vehicle's flight state is left as it is: the FPMa never asks for one (the pilot in
    /// command decides).
    pub async fn resume(&mut self, p: Persisted) {
        let st = p.exec.state();
        tracing::info!(
            plan = %st.plan,
            version = st.version,
            next_seq = st.next_seq,
            last_reached = ?p.last_reached,
            "resuming the persisted plan where it was"
        );
        self.exec = Some(p.exec);
        self.source = p.source;
        // The VAS may have restarted too and forgotten the plan's fence.
        let fence = self
            .exec
            .as_ref()
            .and_then(|ex| ex.plan().fence.as_ref().map(|f| f.fence.clone()));
        if fence.is_some() {
            if let Err(e) = self.vas.set_fence(fence).await {
                tracing::warn!("the VAS did not take the resumed plan's fence: {e}");
            }
        }
        self.pending = p.pending.into();
        self.max_pushed = p.max_pushed;
        self.last_reached = p.last_reached;
        self.taken_over = p.taken_over;
        self.started = Some(Instant::now());
        self.must_flush = true;
        self.after_change().await;
    }

    /// The VAS port (for tests).
    pub fn vas(&self) -> &V {
        &self.vas
    }

    /// The executive, once a plan is loaded.
    pub fn executive(&self) -> Option<&Executive> {
        self.exec.as_ref()
    }

    /// The geometry of the plan version being flown (version 0 before any plan).
    pub fn geometry(&self) -> &PlanGeometry {
        &self.geometry
    }

    /// A VAS call failed and [`Core::sync`] should be retried.
    pub fn needs_retry(&self) -> bool {
        self.dirty || self.must_flush
    }

    /// What to publish since the last call.
    pub fn take_outputs(&mut self) -> Outputs {
        std::mem::take(&mut self.out)
    }

    /// Parses and loads a plan (XML, or a QGroundControl `.plan` when `source` ends so): the
    /// first one starts the executive, later ones replace the plan atomically (a new version).
    /// `source` names the plan in errors: `source:line:col: what`.
    ///
    /// # Errors
    /// The plan does not parse or validate; nothing changes then.
    pub async fn load(&mut self, text: &str, source: &str) -> Result<PlanLoaded, String> {
        let plan = self.check(text, source)?;
        self.start_plan(plan, source).await
    }

    /// Like [`Core::load`] but refused when no plan is loaded (the in-flight `replace_plan`).
    ///
    /// # Errors
    /// No plan to replace, or the new plan is invalid.
    pub async fn replace(&mut self, text: &str, source: &str) -> Result<PlanLoaded, String> {
        if self.exec.is_none() {
            return Err("no plan is loaded: nothing to replace (use load_plan)".into());
        }
        self.load(text, source).await
    }

    /// Parses and checks a plan (the one check its load makes: the plan is flown in simulation
    /// once, and what that gives is kept for the stations' geometry).
    fn check(&self, text: &str, source: &str) -> Result<CheckedPlan, String> {
        flightplan::plan_file::load(text, source, &self.cfg.vehicle).map_err(|e| e.to_string())
    }

    async fn start_plan(&mut self, plan: CheckedPlan, source: &str) -> Result<PlanLoaded, String> {
        let name = plan.plan().name.clone();
        let fence = plan.plan().fence.as_ref().map(|f| f.fence.clone());
        let had_fence = self
            .exec
            .as_ref()
            .is_some_and(|ex| ex.plan().fence.is_some());
        // Before the plan is taken and any of its waypoints goes out, so the VAS checks them
        // against it; a fence the VAS refuses (wider than the vehicle's) refuses the plan.
        if fence.is_some() || had_fence {
            match self.vas.set_fence(fence).await {
                Ok(m) => tracing::info!("fence of plan `{name}`: {m}"),
                Err(FenceRefusal::Refused(why)) => {
                    return Err(format!("{source}: the VAS refused the plan's fence: {why}"))
                }
                Err(e @ FenceRefusal::Unreachable(_)) => tracing::warn!(
                    "the VAS did not take the fence of plan `{name}` (the FPMa checked the plan against it, the VAS checks the vehicle's own): {e}"
                ),
            }
        }
        match &mut self.exec {
            Some(ex) => {
                ex.replace_plan(plan).map_err(|e| e.to_string())?;
            }
            None => {
                self.exec = Some(Executive::from_checked(plan));
            }
        }
        self.started = Some(Instant::now());
        source.clone_into(&mut self.source);
        let version = self.exec.as_ref().map_or(0, Executive::version);
        self.out.events.push(PlanEvent {
            version,
            kind: PlanEventKind::PlanLoaded { name: name.clone() },
        });
        tracing::info!("plan `{name}` loaded as version {version}");
        // A new version: nothing handed out before belongs to it.
        self.must_flush = true;
        self.after_change().await;
        Ok(PlanLoaded {
            version,
            name,
            queued: self.pending.len() as u64,
            navigation_refused: None,
        })
    }

    /// Applies an in-flight command.
    ///
    /// # Errors
    /// No plan loaded, or the executive refused (the reason; nothing changed then).
    pub async fn command(&mut self, cmd: Command) -> Result<CommandAck, String> {
        let ex = self
            .exec
            .as_mut()
            .ok_or("no plan is loaded (load_plan first)")?;
        if cmd == Command::Resume {
            if let Some(by) = self.taken_over.take() {
                // The operator takes the vehicle back: the plan's queue is laid out again.
                tracing::info!("plan resumed by the operator after a takeover ({by})");
                self.must_flush = true;
                if ex.state().paused {
                    ex.resume().map_err(|e| e.to_string())?;
                }
                self.after_change().await;
                return Ok(self.ack());
            }
        }
        let r = match cmd {
            Command::SkipLeg => ex.skip_leg(),
            Command::GotoLeg(id) => ex.goto_leg(&id),
            Command::GotoStage(s) => ex.goto_stage(s),
            Command::SetVar(n, v) => ex.set_var(&n, v),
            Command::HoldHere(h) => ex.hold_here(&h),
            Command::ExitHold(now) => ex.exit_hold(now),
            Command::Pause => ex.pause(),
            Command::Resume => ex.resume(),
            Command::ModifyLeg(id, changes) => ex.modify_leg(&id, &changes).map(drop),
            Command::Retask(points, alt, mode) => ex.retask(&points, alt, mode).map(drop),
            Command::InsertLegs(xml) => ex.insert_legs(&xml).map(drop),
            Command::Emergency(rule) => ex.emergency(rule.as_deref()),
        };
        r.map_err(|e| e.to_string())?;
        // A queue that ran out (completed or paused) and has waypoints again waits for the
        // operator's WAYPOINT_NAVIGATION: `ready` says so.
        self.after_change().await;
        Ok(self.ack())
    }

    fn ack(&self) -> CommandAck {
        let st = self.exec.as_ref().map(Executive::state);
        CommandAck {
            version: st.as_ref().map_or(0, |s| s.version),
            leg: st.as_ref().and_then(|s| s.leg.clone()),
            next_seq: st.as_ref().map_or(0, |s| s.next_seq),
        }
    }

    /// The VAS reports a waypoint reached. Reports for waypoints the executive no longer
    /// expects (an abandoned target, another plan version) are ignored.
    pub async fn on_reached(&mut self, seq: u64) {
        if !self.apply_reached(seq) {
            tracing::debug!("waypoint {seq} reached: not one of the present plan's, ignored");
            return;
        }
        self.after_change().await;
    }

    /// Reports `seq` (and the pending ones before it) to the executive; false when `seq` is
    /// not pending.
    fn apply_reached(&mut self, seq: u64) -> bool {
        let Some(i) = self.pending.iter().position(|(_, w)| w.seq == seq) else {
            return false;
        };
        let Some(&(version, _)) = self.pending.get(i) else {
            return false;
        };
        self.pending.drain(..=i);
        self.last_reached = Some(seq);
        if let Some(ex) = &mut self.exec {
            if let Err(e) = ex.waypoint_reached(version, seq) {
                // Cannot happen while `pending` mirrors the executive; say so if it does.
                tracing::warn!("waypoint {seq}: {e}");
                self.must_flush = true;
            }
        }
        true
    }

    /// Telemetry from the VAS: the present position and the built-in variables.
    pub async fn on_position(&mut self, p: &Position) {
        self.eta.observe(f64::from(p.speed));
        let Some(ex) = &mut self.exec else { return };
        // `alt` is compared with the plan's altitudes, so it is measured from the same
        // reference. The VAS knows no terrain height: above home stands in for above terrain.
        let alt = match ex.plan().altitude_reference() {
            AltRef::Msl => p.alt,
            AltRef::Relative | AltRef::Terrain => p.alt_rel,
        };
        ex.update_telemetry(Telemetry {
            position: Some(GeoPoint::new(p.lat, p.lon)),
            alt: Some(alt),
            ground_speed: Some(f64::from(p.speed)),
            battery: None,
            elapsed_s: self.started.map(|t| t.elapsed().as_secs_f64()),
        });
        self.after_telemetry().await;
    }

    /// Battery state from the VAS: the built-in `battery` (percent remaining) follows it.
    pub async fn on_battery(&mut self, b: &Battery) {
        let Some(ex) = &mut self.exec else { return };
        let Some(remaining) = b.remaining.map(f64::from).filter(|r| r.is_finite()) else {
            return;
        };
        ex.update_telemetry(Telemetry {
            battery: Some(remaining),
            elapsed_s: self.started.map(|t| t.elapsed().as_secs_f64()),
            ..Telemetry::default()
        });
        self.after_telemetry().await;
    }

    async fn after_telemetry(&mut self) {
        let Some(ex) = &mut self.exec else { return };
        // Only an emergency rule firing changes anything here.
        let events = ex.take_events();
        if !events.is_empty() {
            self.collect(events);
            self.after_change().await;
        }
    }

    /// The VAS reports that another ground station wrote the autopilot's mission (`by`, with
    /// `items` items): the vehicle flies that mission now. The plan is paused and nothing more
    /// is handed to the VAS until the operator resumes it ([`Command::Resume`]); stations are
    /// told who took over.
    pub async fn on_mission_changed(&mut self, by: &str, items: u64) {
        let who = format!("{by}, {items} items");
        tracing::warn!("the vehicle flies another ground station's mission ({who}): plan paused until the operator resumes it");
        self.taken_over = Some(who);
        let version = self.exec.as_ref().map_or(0, Executive::version);
        if let Some(ex) = &mut self.exec {
            if !ex.state().paused {
                let _ = ex.pause();
            }
        }
        self.out.events.push(PlanEvent {
            version,
            kind: PlanEventKind::TakenOver {
                by: by.to_owned(),
                items,
            },
        });
        self.after_change().await;
    }

    /// The VAS's flight state changed: only what stations are told changes (the plan waits
    /// for, or no longer waits for, the operator's start).
    pub fn on_flight_state(&mut self, s: FlightState) {
        self.vas_state = Some(s);
        self.update_readiness();
    }

    /// Whether the plan waits for the operator to start it, and what to tell them.
    pub fn readiness(&self) -> Readiness {
        let Some(ex) = &self.exec else {
            return Readiness {
                text: "no plan loaded".into(),
                ..Readiness::default()
            };
        };
        let st = ex.state();
        let name = &st.plan;
        let (ready, text) = if let Some(who) = &self.taken_over {
            (
                false,
                format!("the vehicle flies another ground station's mission ({who}): plan `{name}` paused; resume it to take the vehicle back"),
            )
        } else if st.completed {
            (false, format!("plan `{name}` completed"))
        } else if self.vas_state == Some(FlightState::WaypointNavigation) {
            (false, format!("flying plan `{name}`"))
        } else if self.pending.is_empty() {
            let why = if st.paused {
                "paused"
            } else {
                "loaded, its waypoints not queued at the VAS yet"
            };
            (false, format!("plan `{name}` {why}"))
        } else if matches!(self.vas_state, None | Some(FlightState::ConfigureCheck)) {
            (
                false,
                format!("plan `{name}` loaded, waiting for the VAS to configure the autopilot"),
            )
        } else {
            (
                true,
                format!("plan `{name}` ready, press Start (WAYPOINT_NAVIGATION)"),
            )
        };
        Readiness {
            version: st.version,
            plan: st.plan.clone(),
            ready,
            text,
        }
    }

    fn update_readiness(&mut self) {
        let r = self.readiness();
        if self.readiness.as_ref() != Some(&r) {
            self.readiness = Some(r.clone());
            self.out.readiness = Some(r);
        }
    }

    /// Re-runs a failed synchronisation with the VAS.
    pub async fn retry(&mut self) {
        if self.needs_retry() {
            self.sync().await;
        }
    }

    async fn after_change(&mut self) {
        self.changes += 1;
        self.sync().await;
        if let Some(ex) = &mut self.exec {
            let events = ex.take_events();
            self.collect(events);
        }
        self.publish_state();
    }

    fn collect(&mut self, events: Vec<flightplan::exec::Event>) {
        self.out
            .events
            .extend(events.into_iter().filter_map(PlanEvent::from_exec));
    }

    fn publish_state(&mut self) {
        self.update_readiness();
        let Some(ex) = &self.exec else { return };
        // Geometry only when the plan itself changed: it is the largest value the FPMa
        // publishes, and a skip or a reached waypoint leaves it as it was.
        if ex.version() != self.geometry.version {
            self.geometry = PlanGeometry::of(ex.plan(), &ex.nominal(), ex.version(), &self.source);
            self.out.geometry = Some(self.geometry.clone());
        }
        let st = ex.state();
        let (flown, remaining) = ex.distances_m();
        let planned = flown + remaining;
        let (plan_left, leg_left) = ex.remaining_m();
        let fraction = if st.completed {
            1.0
        } else if planned > 0.0 {
            flown / planned
        } else {
            0.0
        };
        self.out.progress = Some(Progress {
            version: st.version,
            plan: st.plan.clone(),
            stage: st.stage,
            leg: st.leg.clone(),
            last_reached: self.last_reached,
            next_seq: st.next_seq,
            flown_m: flown,
            planned_m: planned,
            fraction,
            paused: st.paused,
            completed: st.completed,
            holding: st.holding,
            eta_s: self.eta.eta_s(plan_left).filter(|_| !st.completed),
            leg_eta_s: self.eta.eta_s(leg_left).filter(|_| !st.completed),
            taken_over: self.taken_over.clone(),
        });
        self.out.state = Some(PlanState {
            version: st.version,
            loops: st.loops,
            vars: st.vars.into_iter().map(|(k, v)| (k, v.into())).collect(),
            queued: self.pending.iter().map(|(_, w)| w.seq).collect(),
        });
    }

    fn desired(&self) -> (u64, Vec<usal_types::Waypoint>) {
        match &self.exec {
            Some(ex) => (
                ex.version(),
                ex.next_waypoints(self.cfg.lookahead)
                    .iter()
                    .map(|w| to_vas(w, ex.plan().altitude_reference()))
                    .collect(),
            ),
            None => (0, Vec::new()),
        }
    }

    /// Brings the VAS queue in line with the executive's look-ahead.
    pub async fn sync(&mut self) {
        if self.exec.is_none() || self.taken_over.is_some() {
            return;
        }
        self.changes += 1;
        self.dirty = false;
        let (version, desired) = self.desired();
        let extends = self.pending.len() <= desired.len()
            && self
                .pending
                .iter()
                .zip(&desired)
                .all(|((v, p), d)| *v == version && p == d);
        if extends && !self.must_flush {
            let tail = desired[self.pending.len()..].to_vec();
            if !tail.is_empty() {
                self.push(version, tail).await;
            }
        } else {
            self.flush().await;
        }
    }

    async fn push(&mut self, version: u64, wps: Vec<usal_types::Waypoint>) -> bool {
        match self.vas.push(wps.clone()).await {
            Ok(_) => {
                self.max_pushed = self.max_pushed.max(wps.last().map(|w| w.seq));
                self.pending.extend(wps.into_iter().map(|w| (version, w)));
                true
            }
            Err(e) => {
                tracing::warn!("push_waypoints: {e}");
                self.dirty = true;
                false
            }
        }
    }

    /// Clears the VAS queue and refills it from the executive's present look-ahead.
    async fn flush(&mut self) {
        let status = match self.vas.clear().await {
            Ok(s) => s,
            Err(e) => {
                tracing::warn!("clear_waypoints: {e}");
                self.must_flush = true;
                self.dirty = true;
                return;
            }
        };
        // A report the VAS made that has not reached us yet: account for it first, so the
        // executive knows where the vehicle is.
        if let Some(seq) = status.last_reached {
            self.apply_reached(seq);
        }
        let (version, mut desired) = self.desired();
        let kept = match (status.target, self.pending.front(), desired.first()) {
            (Some(t), Some((v, p)), Some(d)) => t == p.seq && *v == version && p == d,
            _ => false,
        };
        if !kept {
            // The VAS still drives to its target: number the new waypoints past it and all
            // handed out before, so its report is not taken for a new waypoint.
            if let (Some(max), Some(ex)) = (self.max_pushed, &mut self.exec) {
                ex.skip_seqs_to(max + 1);
            }
            desired = self.desired().1;
        }
        self.pending.clear();
        self.must_flush = false;
        if !self.push(version, desired).await {
            self.must_flush = true;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use flightplan::api::PlanEventKind as K;
    use std::sync::Mutex;

    /// The VAS queue as its README describes it: push appends; after clear, a push replaces
    /// what follows the target (kept while navigating; a first pushed waypoint equal to it is
    /// not repeated); WAYPOINT_NAVIGATION needs queued waypoints.
    #[derive(Default)]
    struct FakeVas {
        st: Mutex<FakeState>,
    }

    #[derive(Default)]
    struct FakeState {
        queue: VecDeque<usal_types::Waypoint>,
        running: bool,
        replacing: bool,
        last_reached: Option<u64>,
        calls: Vec<String>,
        /// What `set_fence` answers a fence with (a VAS whose vehicle fence is narrower).
        fence_refusal: Option<String>,
    }

    impl FakeVas {
        fn st(&self) -> std::sync::MutexGuard<'_, FakeState> {
            self.st.lock().unwrap()
        }
        fn status(s: &FakeState) -> QueueStatus {
            QueueStatus {
                queued: s.queue.len() as u64,
                target: s.queue.front().map(|w| w.seq),
                last_reached: s.last_reached,
                replacing: s.replacing,
                ..Default::default()
            }
        }
        /// The vehicle reaches its target; returns it (the VAS then raises waypoint_reached).
        fn reach(&self) -> Option<usal_types::Waypoint> {
            let mut s = self.st();
            if !s.running {
                return None;
            }
            let w = s.queue.pop_front()?;
            s.last_reached = Some(w.seq);
            if s.queue.is_empty() {
                // HOLD after the last item: PARKING.
                s.running = false;
            }
            Some(w)
        }
        fn seqs(&self) -> Vec<u64> {
            self.st().queue.iter().map(|w| w.seq).collect()
        }
        fn calls(&self) -> Vec<String> {
            std::mem::take(&mut self.st().calls)
        }
        /// The operator's WAYPOINT_NAVIGATION (not the core's: it has no such call).
        fn start(&self) -> bool {
            let mut s = self.st();
            s.running = !s.queue.is_empty();
            s.running
        }
    }

    #[async_trait]
    impl VasPort for FakeVas {
        async fn push(&self, wps: Vec<usal_types::Waypoint>) -> Result<QueueStatus, String> {
            let mut s = self.st();
            s.calls.push(format!("push {}", wps.len()));
            let mut wps = wps.into_iter().peekable();
            if s.replacing {
                s.replacing = false;
                let keep = usize::from(s.running);
                s.queue.truncate(keep);
                if wps.peek().is_some() && wps.peek() == s.queue.front() {
                    wps.next();
                }
            }
            s.queue.extend(wps);
            Ok(Self::status(&s))
        }
        async fn clear(&self) -> Result<QueueStatus, String> {
            let mut s = self.st();
            s.calls.push("clear".into());
            s.replacing = true;
            Ok(Self::status(&s))
        }
        async fn set_fence(
            &self,
            fence: Option<usal_types::Fence>,
        ) -> Result<String, FenceRefusal> {
            let mut s = self.st();
            s.calls.push(format!("set_fence {}", fence.is_some()));
            match (&s.fence_refusal, fence) {
                (Some(why), Some(_)) => Err(FenceRefusal::Refused(why.clone())),
                _ => Ok("fence in force".into()),
            }
        }
    }

    const PLAN: &str = r#"<flightPlan name="t" defaultSpeed="2">
  <fixes>
    <fix id="A" lat="41.27500" lon="1.98700" alt="0"/>
    <fix id="B" lat="41.27540" lon="1.98700" alt="0"/>
    <fix id="C" lat="41.27540" lon="1.98750" alt="0"/>
    <fix id="D" lat="41.27500" lon="1.98750" alt="0"/>
    <fix id="E" lat="41.27470" lon="1.98720" alt="0"/>
  </fixes>
  <departure><leg type="IF" fix="A"/><leg id="b" type="TF" fix="B"/></departure>
  <mission>
    <leg id="c" type="TF" fix="C"/>
    <scan id="area" spacing="6" sweepAngle="90">
      <pt lat="41.27510" lon="1.98710"/> <pt lat="41.27535" lon="1.98710"/>
      <pt lat="41.27535" lon="1.98740"/> <pt lat="41.27510" lon="1.98740"/>
    </scan>
    <leg id="d" type="TF" fix="D"/>
  </mission>
  <approach><leg id="app" type="TF" fix="E"/></approach>
</flightPlan>"#;

    fn core(lookahead: usize) -> Core<FakeVas> {
        Core::new(
            CoreConfig {
                vehicle: VehicleParams::rover(),
                lookahead,
            },
            FakeVas::default(),
        )
    }

    /// What the executive would stream with no changes, as the VAS sees it.
    fn nominal() -> Vec<usal_types::Waypoint> {
        let plan = flightplan::parse::parse_plan(PLAN).unwrap();
        let alt_ref = plan.altitude_reference();
        flightplan::exec::expand_nominal(plan, VehicleParams::rover())
            .unwrap()
            .iter()
            .map(|w| to_vas(w, alt_ref))
            .collect()
    }

    /// The operator starts the plan (when the vehicle is not navigating already), then it
    /// flies until the fake VAS runs out, reporting each reach; returns what was reached.
    async fn fly(c: &mut Core<FakeVas>, at_most: usize) -> Vec<usal_types::Waypoint> {
        if !c.vas().st().running {
            c.vas().start();
        }
        let mut flown = Vec::new();
        while flown.len() < at_most {
            let Some(w) = c.vas().reach() else { break };
            c.on_reached(w.seq).await;
            flown.push(w);
        }
        flown
    }

    fn kinds(c: &mut Core<FakeVas>) -> Vec<K> {
        c.take_outputs()
            .events
            .into_iter()
            .map(|e| e.kind)
            .collect()
    }

    /// A core on `vas` (the VAS a previous core fed: it went on without it).
    fn core_on(vas: FakeVas) -> Core<FakeVas> {
        Core::new(
            CoreConfig {
                vehicle: VehicleParams::rover(),
                lookahead: 4,
            },
            vas,
        )
    }

    /// The state as it comes back from disk.
    fn saved(c: &Core<FakeVas>) -> Persisted {
        let json = serde_json::to_string(&c.snapshot().expect("a plan")).unwrap();
        serde_json::from_str(&json).unwrap()
    }

    #[tokio::test]
    async fn a_resumed_core_goes_on_where_it_was_without_asking_to_navigate() {
        let mut c = core_on(FakeVas::default());
        assert!(c.snapshot().is_none(), "nothing to persist before a plan");
        c.load(PLAN, "plan").await.unwrap();
        let mut flown = fly(&mut c, 3).await;
        let state = saved(&c);
        // While the FPMa is down the VAS goes on: one more waypoint reached unheard.
        flown.extend(c.vas().reach());
        let vas = std::mem::take(&mut c.vas);
        vas.calls();
        let mut r = core_on(vas);
        r.resume(state).await;
        let calls = r.vas().calls();
        assert_eq!(
            calls.first().map(String::as_str),
            Some("clear"),
            "{calls:?}"
        );
        assert!(
            !calls.iter().any(|c| c.starts_with("state")),
            "resuming asked for a flight state: {calls:?}"
        );
        flown.extend(fly(&mut r, 100).await);
        assert!(r.executive().unwrap().state().completed);
        // Each waypoint of the plan once, in order.
        let got: Vec<(f64, f64)> = flown.iter().map(|w| (w.lat, w.lon)).collect();
        let want: Vec<(f64, f64)> = nominal().iter().map(|w| (w.lat, w.lon)).collect();
        assert_eq!(got, want);
    }

    #[tokio::test]
    async fn a_restarted_fpma_still_leaves_another_station_s_mission_alone() {
        let mut c = core_on(FakeVas::default());
        c.load(PLAN, "plan").await.unwrap();
        fly(&mut c, 2).await;
        c.on_mission_changed("MAVLink system 250 component 190", 4)
            .await;
        let state = saved(&c);
        let vas = std::mem::take(&mut c.vas);
        vas.calls();
        let mut r = core_on(vas);
        r.resume(state).await;
        assert!(
            r.vas().calls().is_empty(),
            "the restarted FPMa wrote to the VAS"
        );
        let p = r.take_outputs().progress.expect("progress published");
        assert!(p.taken_over.is_some_and(|t| t.contains("system 250")));
        r.command(Command::Resume).await.unwrap();
        assert_eq!(r.vas().calls().first().map(String::as_str), Some("clear"));
    }

    #[tokio::test]
    async fn the_persisted_state_keeps_in_flight_changes() {
        let mut c = core_on(FakeVas::default());
        c.load(PLAN, "plan").await.unwrap();
        fly(&mut c, 2).await;
        c.command(Command::SkipLeg).await.unwrap();
        c.command(Command::ModifyLeg(
            "area".into(),
            vec![("spacing".into(), "10".into())],
        ))
        .await
        .unwrap();
        let state = saved(&c);
        let before = c.executive().unwrap();
        assert_eq!(state.exec.next_waypoints(50), before.next_waypoints(50));
        assert_eq!(state.exec.state(), before.state());
        assert_eq!(state.exec.version(), 2, "modify_leg made a version 2");
    }

    #[tokio::test]
    async fn resuming_leaves_a_parked_vehicle_parked() {
        let mut c = core_on(FakeVas::default());
        c.load(PLAN, "plan").await.unwrap();
        fly(&mut c, 2).await;
        let state = saved(&c);
        // The operator parked the vehicle while the FPMa was down.
        let vas = std::mem::take(&mut c.vas);
        vas.st().running = false;
        vas.calls();
        let mut r = core_on(vas);
        r.resume(state).await;
        r.on_flight_state(FlightState::Parking);
        let calls = r.vas().calls();
        assert!(
            !calls.iter().any(|c| c.starts_with("state")),
            "resuming asked for a flight state: {calls:?}"
        );
        assert_eq!(r.executive().unwrap().state().next_seq, 2);
        assert!(!r.vas().seqs().is_empty(), "the queue was refilled");
    }

    #[tokio::test]
    async fn a_loaded_plan_fills_the_queue_waits_for_the_operator_and_flies_to_the_end() {
        let mut c = core(4);
        c.on_flight_state(FlightState::Parking);
        let loaded = c.load(PLAN, "t.xml").await.unwrap();
        assert_eq!((loaded.version, loaded.queued), (1, 4));
        assert_eq!(loaded.navigation_refused, None);
        // The queue is filled, and no flight state asked for: that is the operator's.
        assert_eq!(c.vas().calls(), ["clear", "push 4"]);
        assert!(
            c.vas().reach().is_none(),
            "the vehicle does not move by itself"
        );
        assert_eq!(c.vas().seqs(), [0, 1, 2, 3]);
        let out = c.take_outputs();
        assert!(matches!(&out.events[0].kind, K::PlanLoaded { name } if name == "t"));
        assert_eq!(out.progress.as_ref().map(|p| p.fraction), Some(0.0));
        let r = out.readiness.expect("readiness published");
        assert!(r.ready && r.text.contains("press Start"), "{r:?}");
        // The operator starts it: no longer "ready".
        c.on_flight_state(FlightState::WaypointNavigation);
        let r = c.take_outputs().readiness.expect("readiness changed");
        assert!(!r.ready && r.text.contains("flying"), "{r:?}");

        let flown = fly(&mut c, 1000).await;
        assert_eq!(flown, nominal(), "the nominal stream, in order, once");
        // Refilled one at a time: the queue never held more than the look-ahead.
        assert!(c.vas().calls().iter().all(|k| k == "push 1"));
        let out = c.take_outputs();
        assert!(out.events.iter().any(|e| e.kind == K::PlanCompleted));
        let p = out.progress.unwrap();
        assert!(p.completed && p.fraction == 1.0, "{p:?}");
        assert!(p.flown_m > 100.0 && (p.planned_m - p.flown_m).abs() < 1e-6);
    }

    #[tokio::test]
    async fn geometry_is_published_when_the_plan_changes_only() {
        let mut c = core(4);
        assert_eq!(c.geometry().version, 0);
        c.load(PLAN, "t.xml").await.unwrap();
        let g = c
            .take_outputs()
            .geometry
            .expect("geometry of the loaded plan");
        assert_eq!(
            (g.version, g.name.as_str(), g.source.as_str()),
            (1, "t", "t.xml")
        );
        assert_eq!(g.points.len(), nominal().len());
        assert_eq!(c.geometry(), &g);
        let scan_points = |g: &PlanGeometry| {
            g.points
                .iter()
                .filter(|p| g.leg_of(p).is_some_and(|l| l.id == "area"))
                .count()
        };
        // Flying and skipping change progress, not the plan: no geometry.
        fly(&mut c, 2).await;
        c.command(Command::SkipLeg).await.unwrap();
        let out = c.take_outputs();
        assert!(out.progress.is_some() && out.geometry.is_none());
        // A modified leg is a new version: new geometry, with the scan redrawn.
        c.command(Command::ModifyLeg(
            "area".into(),
            vec![("spacing".into(), "12".into())],
        ))
        .await
        .unwrap();
        let g2 = c
            .take_outputs()
            .geometry
            .expect("geometry of the new version");
        assert_eq!(g2.version, 2);
        assert!(
            scan_points(&g2) < scan_points(&g),
            "wider spacing, fewer points"
        );
        let area = g2.legs.iter().find(|l| l.id == "area").unwrap();
        assert!(area.params.contains(&("spacing".into(), 12.0)));
    }

    #[tokio::test]
    async fn skip_leg_clears_the_queue_and_numbers_the_new_waypoints_past_the_old() {
        let mut c = core(4);
        c.load(PLAN, "t.xml").await.unwrap();
        // A reached, on the way to B (the `b` leg); C and the scan are queued.
        fly(&mut c, 1).await;
        let _ = c.vas().calls();
        let _ = c.take_outputs();
        let before = c.vas().seqs();
        let ack = c.command(Command::SkipLeg).await.unwrap();
        assert_eq!((ack.version, ack.leg.as_deref()), (1, Some("c")));
        assert_eq!(c.vas().calls(), ["clear", "push 4"]);
        // The VAS keeps its target (B); then come the new waypoints, numbered past the old.
        let after = c.vas().seqs();
        assert_eq!(after[0], before[0]);
        let max_before = *before.iter().max().unwrap();
        assert!(
            after[1..].iter().all(|&s| s > max_before),
            "{before:?} {after:?}"
        );
        let evs = kinds(&mut c);
        assert!(evs.contains(&K::LegCompleted {
            leg: "b".into(),
            skipped: true
        }));
        // B is flown (the VAS could not take it back) but not counted; C is next.
        let flown = fly(&mut c, 2).await;
        assert_eq!(flown[0].leg, "b");
        assert_eq!(flown[1].leg, "c");
        let ex = c.executive().unwrap();
        assert_eq!(ex.state().leg.as_deref(), Some("area"));
        let rest = fly(&mut c, 1000).await;
        let nominal = nominal();
        let tail: Vec<_> = nominal.iter().skip_while(|w| w.leg != "area").collect();
        assert_eq!(rest.len(), tail.len());
        assert!(rest
            .iter()
            .zip(tail)
            .all(|(a, b)| a.lat == b.lat && a.lon == b.lon && a.leg == b.leg));
    }

    #[tokio::test]
    async fn modify_leg_refills_from_the_new_version_only() {
        let mut c = core(4);
        c.load(PLAN, "t.xml").await.unwrap();
        fly(&mut c, 3).await; // A, B, C: the scan is being flown.
        assert_eq!(c.executive().unwrap().state().leg.as_deref(), Some("area"));
        let _ = c.vas().calls();
        let ack = c
            .command(Command::ModifyLeg(
                "area".into(),
                vec![("spacing".into(), "10".into())],
            ))
            .await
            .unwrap();
        assert_eq!(ack.version, 2);
        assert_eq!(c.vas().calls(), ["clear", "push 4"]);
        assert!(kinds(&mut c).contains(&K::PlanModified { leg: "area".into() }));
        // Everything pending is of version 2.
        assert!(c.pending.iter().all(|(v, _)| *v == 2));
        let rest = fly(&mut c, 1000).await;
        let scan6 = nominal().iter().filter(|w| w.leg == "area").count();
        // The abandoned target is flown once more, then the wider scan (fewer tracks).
        let scan10 = rest.iter().skip(1).filter(|w| w.leg == "area").count();
        assert!(scan10 < scan6, "{scan10} vs {scan6}");
        assert_eq!(rest.last().unwrap().leg, "app");
        assert!(c.executive().unwrap().state().completed);
    }

    #[tokio::test]
    async fn a_plan_whose_fence_the_vas_refuses_is_not_loaded_and_the_flown_plan_stays() {
        let mut c = core(3);
        c.load(PLAN, "first.xml").await.unwrap();
        let before = c.executive().map(Executive::version);
        c.vas().st().fence_refusal = Some("the plan's fence circle reaches outside".into());
        let fenced = PLAN.replace("</mission>", r#"</mission><fence maxDistance="500"/>"#);
        let e = c.load(&fenced, "wide.xml").await.unwrap_err();
        assert_eq!(
            e,
            "wide.xml: the VAS refused the plan's fence: the plan's fence circle reaches outside"
        );
        assert_eq!(c.executive().map(Executive::version), before);
        assert_eq!(c.executive().map(|ex| ex.plan().name.as_str()), Some("t"));
        assert!(c.executive().is_some_and(|ex| ex.plan().fence.is_none()));
        c.vas().st().fence_refusal = None;
        c.load(&fenced, "fits.xml").await.unwrap();
        assert!(c.executive().is_some_and(|ex| ex.plan().fence.is_some()));
    }

    #[tokio::test]
    async fn a_plan_that_never_ends_is_refused() {
        let mut c = core(3);
        let endless = PLAN.replace(
            r#"<leg id="d" type="TF" fix="D"/>"#,
            r#"<iterative count="4000000000"><leg id="d" type="TF" fix="D"/><leg type="TF" fix="C"/></iterative>"#,
        );
        let e = c.load(&endless, "loop.xml").await.unwrap_err();
        assert!(
            e.starts_with("loop.xml: ") && e.contains("without ending"),
            "{e}"
        );
        assert!(c.executive().is_none() && c.vas().calls().is_empty());
    }

    #[tokio::test]
    async fn insert_legs_refills_the_queue_with_the_inserted_legs() {
        let mut c = core(3);
        c.load(PLAN, "t.xml").await.unwrap();
        let before = c.executive().unwrap().next_waypoints(1)[0].leg.clone();
        let e = c
            .command(Command::InsertLegs(r#"<leg type="TF" fix="NOPE"/>"#.into()))
            .await
            .unwrap_err();
        assert!(e.contains("1:") && e.contains("unknown fix `NOPE`"), "{e}");
        let _ = c.vas().calls();
        let ack = c
            .command(Command::InsertLegs(
                r#"<leg id="x" type="TF" fix="D"/>"#.into(),
            ))
            .await
            .unwrap();
        assert_eq!(ack.version, 2);
        assert!(c.vas().calls().contains(&"clear".to_string()));
        // Behind the target the VAS keeps, the new look-ahead: A, then the inserted leg.
        let queued: Vec<String> = c.vas().st().queue.iter().map(|w| w.leg.clone()).collect();
        assert_eq!(
            queued[queued.len() - 3..],
            [before, "x".to_string(), "b".to_string()],
            "{queued:?}"
        );
    }

    #[tokio::test]
    async fn refusals_come_back_with_the_reason_and_change_nothing() {
        let mut c = core(4);
        let e = c.command(Command::SkipLeg).await.unwrap_err();
        assert!(e.contains("no plan is loaded"), "{e}");
        let e = c.replace(PLAN, "plan").await.unwrap_err();
        assert!(e.contains("nothing to replace"), "{e}");
        let bad = PLAN.replace(r#"fix="D""#, r#"fix="Z""#);
        let e = c.load(&bad, "plan").await.unwrap_err();
        assert!(e.starts_with("plan:16:27:"), "names the line: {e}");
        assert!(e.contains("unknown fix `Z`"), "{e}");
        assert!(c.vas().calls().is_empty());

        c.load(PLAN, "t.xml").await.unwrap();
        let _ = c.vas().calls();
        for (cmd, want) in [
            (Command::GotoLeg("nope".into()), "unknown leg `nope`"),
            (Command::ExitHold(false), "not a hold"),
            (Command::Resume, "not paused"),
            (
                Command::SetVar("x".into(), Value::Bool(true)),
                "unknown variable",
            ),
            (
                Command::ModifyLeg("area".into(), vec![("spacing".into(), "0.5".into())]),
                "invalid plan",
            ),
        ] {
            let e = c.command(cmd).await.unwrap_err();
            assert!(e.contains(want), "{e} / {want}");
        }
        assert!(
            c.vas().calls().is_empty(),
            "a refused command leaves the VAS alone"
        );
        assert_eq!(c.executive().unwrap().version(), 1);
        let bad = PLAN.replace("spacing=\"6\"", "spacing=\"x\"");
        let e = c.replace(&bad, "new.xml").await.unwrap_err();
        assert!(e.starts_with("new.xml:"), "{e}");
        assert_eq!(c.vas().seqs(), [0, 1, 2, 3], "the old plan flies on");
    }

    #[tokio::test]
    async fn replace_plan_bumps_the_version_and_the_old_reports_are_ignored() {
        let mut c = core(3);
        c.load(PLAN, "t.xml").await.unwrap();
        fly(&mut c, 2).await;
        let other = PLAN.replace(r#"name="t""#, r#"name="u""#);
        let loaded = c.replace(&other, "u.xml").await.unwrap();
        assert_eq!((loaded.version, loaded.name.as_str()), (2, "u"));
        // The old target stays at the VAS; what follows is version 2, numbered afresh.
        let q = c.vas().seqs();
        assert_eq!(q.len(), 4);
        assert!(q[1..].iter().all(|&s| s > 4));
        let old = c.vas().reach().unwrap();
        c.on_reached(old.seq).await;
        assert_eq!(c.executive().unwrap().state().next_seq, q[1]);
        // The vehicle is at B: the new plan's IF A and TF B are behind it (the executive
        // drops waypoints closer than the minimum distance), so it flies on from C.
        let rest = fly(&mut c, 1000).await;
        let legs: Vec<&str> = rest.iter().map(|w| w.leg.as_str()).collect();
        let nominal = nominal();
        let want: Vec<&str> = nominal.iter().skip(2).map(|w| w.leg.as_str()).collect();
        assert_eq!(legs, want);
    }

    #[tokio::test]
    async fn pause_lets_the_queue_run_out_and_resume_drives_on() {
        let mut c = core(4);
        c.load(PLAN, "t.xml").await.unwrap();
        fly(&mut c, 1).await;
        let _ = c.vas().calls();
        c.command(Command::Pause).await.unwrap();
        assert_eq!(c.vas().calls(), ["clear", "push 0"]);
        assert_eq!(c.vas().seqs().len(), 1, "only the target is left");
        let w = c.vas().reach().unwrap();
        c.on_reached(w.seq).await;
        assert!(c.vas().reach().is_none(), "stopped");
        c.on_flight_state(FlightState::Parking);
        c.command(Command::Resume).await.unwrap();
        // Refilled, and waiting for the operator to drive on.
        assert_eq!(c.vas().calls(), ["push 4"]);
        assert!(c.readiness().ready, "{:?}", c.readiness());
        let rest = fly(&mut c, 1000).await;
        assert_eq!(rest.last().unwrap().leg, "app");
    }

    #[tokio::test]
    async fn a_takeover_stops_every_call_to_the_vas_until_the_operator_resumes() {
        let mut c = core(4);
        c.load(PLAN, "t.xml").await.unwrap();
        fly(&mut c, 1).await;
        let _ = c.vas().calls();
        let _ = c.take_outputs();
        c.on_mission_changed("MAVLink system 250 component 190", 4)
            .await;
        assert!(
            c.vas().calls().is_empty(),
            "nothing written over the other mission"
        );
        let out = c.take_outputs();
        assert!(
            out.events.iter().any(|e| e.kind
                == PlanEventKind::TakenOver {
                    by: "MAVLink system 250 component 190".into(),
                    items: 4
                }),
            "{:?}",
            out.events
        );
        let p = out.progress.expect("progress published");
        assert!(p.paused);
        assert_eq!(
            p.taken_over.as_deref(),
            Some("MAVLink system 250 component 190, 4 items")
        );
        let r = c.readiness();
        assert!(
            !r.ready && r.text.contains("another ground station"),
            "{r:?}"
        );
        // Reaches, telemetry and the retry tick change nothing at the VAS meanwhile.
        c.on_flight_state(FlightState::Parking);
        c.retry().await;
        assert!(c.vas().calls().is_empty());
        // The operator takes the vehicle back: the plan's queue is laid out again.
        c.command(Command::Resume).await.unwrap();
        let calls = c.vas().calls();
        assert_eq!(
            calls.first().map(String::as_str),
            Some("clear"),
            "{calls:?}"
        );
        let p = c.take_outputs().progress.expect("progress published");
        assert!(!p.paused && p.taken_over.is_none(), "{p:?}");
        assert!(c.readiness().ready, "{:?}", c.readiness());
    }

    #[tokio::test]
    async fn a_report_still_in_flight_at_a_clear_is_accounted_for() {
        let mut c = core(4);
        c.load(PLAN, "t.xml").await.unwrap();
        assert!(c.vas().start());
        // The VAS reaches A and B but the reports are not delivered before the command.
        let a = c.vas().reach().unwrap();
        let b = c.vas().reach().unwrap();
        c.command(Command::SkipLeg).await.unwrap();
        // The clear's status said B was reached: the executive skipped `c`, not `b`.
        let st = c.executive().unwrap().state();
        assert_eq!(st.leg.as_deref(), Some("area"));
        // The late reports change nothing.
        c.on_reached(a.seq).await;
        c.on_reached(b.seq).await;
        assert_eq!(c.executive().unwrap().state().leg.as_deref(), Some("area"));
    }

    #[tokio::test]
    async fn from_manual_navigation_or_directed_a_loaded_plan_only_waits() {
        for state in [FlightState::ManualNavigation, FlightState::Directed] {
            let mut c = core(4);
            c.on_flight_state(state);
            let loaded = c.load(PLAN, "t.xml").await.unwrap();
            assert_eq!(loaded.navigation_refused, None);
            assert_eq!(c.vas().calls(), ["clear", "push 4"], "{state}");
            let r = c.readiness();
            assert!(r.ready && r.plan == "t" && r.version == 1, "{r:?}");
        }
    }

    #[tokio::test]
    async fn a_qgc_plan_is_loaded_by_its_extension() {
        let rover = VehicleParams::rover();
        let plan = flightplan::parse::parse_plan(PLAN).unwrap();
        let doc = flightplan::qgc::export(&plan, &rover).unwrap();
        let mut c = core(4);
        let loaded = c.load(&doc.to_string(), "survey.plan").await.unwrap();
        assert_eq!((loaded.version, loaded.queued), (1, 4));
        let e = c.load("{}", "x.plan").await.unwrap_err();
        assert!(e.starts_with("x.plan: "), "{e}");
        assert_eq!(c.executive().unwrap().version(), 1);
    }

    #[tokio::test]
    async fn readiness_waits_for_the_vas_to_be_configured() {
        let mut c = core(4);
        assert_eq!(c.readiness().text, "no plan loaded");
        c.on_flight_state(FlightState::ConfigureCheck);
        c.load(PLAN, "t.xml").await.unwrap();
        assert_eq!(c.vas().calls(), ["clear", "push 4"]);
        let r = c.readiness();
        assert!(!r.ready && r.text.contains("configure"), "{r:?}");
        c.on_flight_state(FlightState::Parking);
        assert!(c.readiness().ready);
        assert!(c.vas().calls().is_empty(), "no call to the VAS");
        fly(&mut c, 1000).await;
        let r = c.readiness();
        assert!(!r.ready && r.text.contains("completed"), "{r:?}");
    }
}
