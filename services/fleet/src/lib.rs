//! The fleet mission layer (seeds 001 EAMOS and 002 Broz): runs a *fleet plan* (`plan`, format
//! in `services/fleet/README.md`) of EAMOS-style statements — `seq`, `par`, `wait` for an event
//! or a condition on variables, `repeat`, `if`/`else`, `sync` points, the Broz `investigate` —
//! over the flight plans of several vehicles, and keeps them apart (`separation`).
//!
//! **Why a service of its own** (and not part of the launcher's station): the fleet layer is
//! flight logic that must go on whatever watches it. As a process on the ground node it is
//! started, restarted and stopped by `usal run` like every other service (it is started when
//! the mission has a `<fleet>`), it reaches the vehicles only through their public marea items
//! (the FPMa's `load_plan`/`goto_leg`/`progress`, the VAS's `change_state`/`position`/
//! `flight_state`/`alarm`), so it works across the radio gateway like any station, and what it
//! knows is one variable (`<ns>/fleet/status`) that the launcher, the FMo and the FPMo all read
//! — the launcher stays a supervisor and a reporter.
//!
//! Layers: [`plan`] parses and checks a fleet plan (line and column in every error);
//! [`search`] is the investigator's nearest-neighbour choice and [`separation`] the distance
//! monitor, both pure; [`api`] the wire types; this file the executor on a middleware node.
//!
//! Detections come from the vehicles' detectors as the VAS's typed `detection` event (position,
//! confidence, which vehicle: `usal_types::PoiDetection`; a mavsim detector sends it as a
//! STATUSTEXT the VAS reads back, see `sim/src/detector.rs`).
//! Holds (separation, `pause`) put the vehicle's VAS in PARKING (the autopilot's HOLD: the
//! vehicle stops where it is, its waypoint queue kept) and release it with
//! WAYPOINT_NAVIGATION; every plan started is followed by an explicit WAYPOINT_NAVIGATION, so
//! the layer does not rely on the FPMa starting a loaded plan by itself.
//!
//! ```no_run
//! # async fn f() -> anyhow::Result<()> {
//! let plan = fleet::plan::load(std::path::Path::new("config/fleetplans/search.xml"))
//!     .map_err(anyhow::Error::msg)?;
//! let config = fleet::FleetConfig::new(plan);
//! fleet::run(config, tokio_util::sync::CancellationToken::new()).await
//! # }
//! ```

pub mod plan;
pub mod points;
pub mod search;
pub mod separation;
pub mod wavefront;

use std::collections::{HashMap, HashSet};
use std::future::Future;
use std::path::PathBuf;
use std::pin::Pin;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context};
use flightplan::aircraft::{self, AircraftPlan, FlightRecord};
use flightplan::api::items as fpma;
use flightplan::api::{CommandAck, PlanEventKind, PlanLoaded};
use flightplan::expr::Value;
use marea::{CallError, Function, NetworkConfig, Node, Service};
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use usal_types::items::vas;
use usal_types::{AllowedChanges, FlightState, Position, StateChangeReply, StateChangeRequest};

use crate::plan::{Block, BlockKind, FleetPlan, WaitEvent};
use crate::separation::{Action, Monitor};
use flightplan::fleet_api::items as fleet;
use flightplan::fleet_api::{Detection, FleetStatus, VehicleStatus};

/// Everything the service needs.
#[derive(Clone, Debug)]
pub struct FleetConfig {
    /// The fleet plan.
    pub plan: FleetPlan,
    /// A network.xml; default Ethernet on loopback.
    pub network: Option<PathBuf>,
    /// Node name.
    pub node: String,
    /// Discovery domain (overrides the network file's).
    pub domain: Option<String>,
    /// Namespace of the service's items (`gcs` → `gcs/fleet/status`).
    pub namespace: Option<String>,
    /// Time limit of each call to a vehicle.
    pub call_timeout: Duration,
    /// How long a vehicle's services may take to appear before the plan fails.
    pub discovery_timeout: Duration,
}

impl FleetConfig {
    /// Defaults around `plan`.
    pub fn new(plan: FleetPlan) -> Self {
        Self {
            plan,
            network: None,
            node: "fleet".into(),
            domain: None,
            namespace: None,
            call_timeout: Duration::from_secs(5),
            discovery_timeout: Duration::from_secs(90),
        }
    }
}

/// Status publication: at most this often on changes...
const STATUS_MIN_PERIOD: Duration = Duration::from_millis(250);
/// ...and at least this often.
const STATUS_PERIOD: Duration = Duration::from_secs(2);
/// A refused WAYPOINT_NAVIGATION is asked again this often (the VAS refuses while its queue is
/// still being filled or the autopilot is configuring).
const NAV_RETRY: Duration = Duration::from_millis(500);
/// ...this many times.
const NAV_ATTEMPTS: u32 = 20;
/// A detection nearer than this to the investigator counts as visited without a plan (the
/// FPMa drops waypoints closer than a rover's minimum waypoint distance).
const VISIT_RADIUS_M: f64 = 4.0;
/// How long an aircraft's landing (from its plan's last waypoint to parked on the ground,
/// disarmed) and a step of its start (the VAS's state, the first waypoints queued) may take, s.
const LANDING_WAIT_S: f64 = 300.0;
const STEP_WAIT_S: f64 = 60.0;
/// How long a take-off's climb may take, s.
const CLIMB_WAIT_S: f64 = 300.0;

/// Runs the fleet plan until it ends, then keeps publishing the final status until
/// `shutdown`; prints `FLEET_DONE=<status as JSON>` (or `FLEET_FAILED=`) on stdout when the
/// plan ends.
///
/// # Errors
/// When the node cannot be opened or items declared. A plan that fails is not an error of
/// the service: it is reported in the status (`failed`), and the service keeps running.
pub async fn run(config: FleetConfig, shutdown: CancellationToken) -> anyhow::Result<()> {
    let mut net = NetworkConfig::for_service(
        config.network.as_deref(),
        &config.node,
        config.domain.as_deref(),
        config.namespace.as_deref(),
    )
    .context("loading the network configuration")?;
    net.node.clone_from(&config.node);
    let node = Node::open(&net).await.context("joining the network")?;
    let svc = node.service("fleet")?;
    let fleet = Arc::new(Fleet::new(svc.clone(), &config)?);
    let tasks = TaskTracker::new();
    fleet.watch_vehicles(&tasks, &shutdown)?;
    let status_var = fleet::STATUS.publish(&svc)?;
    {
        let fleet = fleet.clone();
        let stop = shutdown.clone();
        tasks.spawn(async move { fleet.publish_status(status_var, stop).await });
    }
    let _pause = {
        let f = fleet.clone();
        fleet::PAUSE.provide(&svc, move |id: String| {
            let f = f.clone();
            async move { f.command_pause(&id, true).await }
        })?
    };
    let _edit_points = {
        let f = fleet.clone();
        fleet::EDIT_POINTS.provide(&svc, move |edit| {
            let f = f.clone();
            async move { f.edit_points(edit) }
        })?
    };
    let _resume = {
        let f = fleet.clone();
        fleet::RESUME.provide(&svc, move |id: String| {
            let f = f.clone();
            async move { f.command_pause(&id, false).await }
        })?
    };
    tracing::info!(plan = %config.plan.name, "fleet plan started");
    let outcome = tokio::select! {
        r = fleet.exec(&config.plan.body) => Some(r),
        () = shutdown.cancelled() => None,
    };
    if let Some(r) = outcome {
        {
            let mut st = fleet.state();
            st.ended = Some(fleet.started.elapsed().as_secs_f64());
            match &r {
                Ok(()) => st.done = true,
                Err(e) => st.failed = Some(format!("{e:#}")),
            }
            st.doing.clear();
        }
        fleet.bump();
        let status = fleet.status();
        let line = serde_json::to_string(&status).unwrap_or_default();
        match r {
            Ok(()) => {
                tracing::info!("fleet plan `{}` completed", status.plan);
                println!("FLEET_DONE={line}");
            }
            Err(e) => {
                tracing::error!("fleet plan `{}` failed: {e:#}", status.plan);
                println!("FLEET_FAILED={line}");
            }
        }
        shutdown.cancelled().await;
    }
    tasks.close();
    tasks.wait().await;
    node.shutdown().await;
    Ok(())
}

/// One vehicle's functions.
struct Vehicle {
    load_plan: Function<String, PlanLoaded>,
    goto_leg: Function<String, CommandAck>,
    change_state: Function<StateChangeRequest, StateChangeReply>,
}

/// What the fleet layer knows of one vehicle.
#[derive(Default)]
struct VehState {
    flight_state: Option<FlightState>,
    position: Option<(f64, f64)>,
    /// The last position report whole (altitudes included).
    last: Option<Position>,
    /// What the VAS allows from its present state.
    allowed: Option<AllowedChanges>,
    /// Waypoints queued at the VAS.
    queued: u64,
    /// An aircraft: the plan it flies now, checked for take-off and climb.
    current: Option<AircraftPlan>,
    /// An aircraft: its plans so far as one flight, and the flight recorded against them.
    flight: Option<(AircraftPlan, FlightRecord)>,
    plan: Option<String>,
    /// The version of the plan last loaded by us.
    version: Option<u64>,
    progress: f64,
    done: bool,
    completions: u64,
    /// We asked for navigation and the plan has not completed: a release restarts it.
    wants_nav: bool,
    held: bool,
    paused: bool,
    /// The nominal waypoints of its plan, for the stations' maps.
    route: Vec<(f64, f64)>,
    /// The static obstacle it is inside now, if any (an entry is counted once).
    inside: Option<String>,
}

#[derive(Default)]
struct State {
    vars: HashMap<String, Value>,
    vs: Vec<VehState>,
    detections: Vec<Detection>,
    /// Detections an investigator is on its way to.
    claimed: HashSet<usize>,
    visit_order: Vec<u32>,
    /// The pending points the operator put first, in order.
    visit_first: Vec<(String, u32)>,
    monitor: Option<Monitor>,
    barriers: HashMap<String, (usize, u64)>,
    doing: Vec<String>,
    done: bool,
    failed: Option<String>,
    ended: Option<f64>,
    /// Times a vehicle entered a static obstacle.
    obstacle_entries: u32,
    /// Visits routed round an obstacle.
    detours: u32,
}

type Exec<'a> = Pin<Box<dyn Future<Output = anyhow::Result<()>> + Send + 'a>>;

struct Fleet {
    plan: FleetPlan,
    vehicles: Vec<Vehicle>,
    st: Mutex<State>,
    changed: watch::Sender<u64>,
    started: Instant,
    svc: Service,
    call_timeout: Duration,
    discovery_timeout: Duration,
}

impl Fleet {
    fn new(svc: Service, config: &FleetConfig) -> anyhow::Result<Self> {
        let plan = config.plan.clone();
        let mut vehicles = Vec::new();
        for v in &plan.vehicles {
            let (fpma_at, vas_at) = (format!("{}/fpma", v.prefix), format!("{}/vas", v.prefix));
            vehicles.push(Vehicle {
                load_plan: fpma::LOAD_PLAN.function(&svc, &fpma_at)?,
                goto_leg: fpma::GOTO_LEG.function(&svc, &fpma_at)?,
                change_state: vas::CHANGE_STATE.function(&svc, &vas_at)?,
            });
        }
        let st = State {
            vars: plan.vars.iter().cloned().collect(),
            vs: plan.vehicles.iter().map(|_| VehState::default()).collect(),
            monitor: plan
                .separation
                .map(|r| Monitor::new(r, plan.vehicles.iter().map(|v| v.priority).collect())),
            ..State::default()
        };
        Ok(Self {
            plan,
            vehicles,
            st: Mutex::new(st),
            changed: watch::channel(0).0,
            started: Instant::now(),
            svc,
            call_timeout: config.call_timeout,
            discovery_timeout: config.discovery_timeout,
        })
    }

    /// The shared state; a panic elsewhere while holding it leaves nothing worth stopping for.
    fn state(&self) -> MutexGuard<'_, State> {
        marea::sync::lock(&self.st)
    }

    /// Something changed: wake the waiters and the status publisher.
    fn bump(&self) {
        self.changed.send_modify(|n| *n = n.wrapping_add(1));
    }

    fn elapsed(&self) -> f64 {
        self.started.elapsed().as_secs_f64()
    }

    /// The value of a name in a condition.
    fn var(&self, st: &State, name: &str) -> Option<Value> {
        if let Some(v) = st.vars.get(name) {
            return Some(*v);
        }
        let visited = st.detections.iter().filter(|d| d.visited.is_some()).count();
        let pending = st.detections.iter().filter(|d| points::pending(d)).count();
        let n = |x: usize| Some(Value::Number(x as f64));
        match name {
            "detections" => return n(st.detections.len()),
            "visited" => return n(visited),
            "pending" => return n(pending),
            "elapsed_s" => return Some(Value::Number(self.elapsed())),
            _ => {}
        }
        let (veh, field) = name.split_once('.')?;
        let i = self.plan.vehicle(veh)?;
        let v = &st.vs[i];
        match field {
            "done" => Some(Value::Bool(v.done)),
            "holding" => Some(Value::Bool(v.held)),
            "paused" => Some(Value::Bool(v.paused)),
            "progress" => Some(Value::Number(v.progress)),
            _ => None,
        }
    }

    fn holds(&self, cond: &flightplan::expr::Condition) -> bool {
        let st = self.state();
        cond.holds(&|n| self.var(&st, n))
    }

    /// Waits until `pred` holds on the state (or `timeout`).
    async fn wait_for(
        &self,
        timeout: Option<f64>,
        what: &str,
        pred: impl Fn(&State) -> bool,
    ) -> anyhow::Result<()> {
        let mut rx = self.changed.subscribe();
        let deadline = timeout.map(|t| tokio::time::Instant::now() + Duration::from_secs_f64(t));
        loop {
            rx.borrow_and_update();
            if pred(&self.state()) {
                return Ok(());
            }
            match deadline {
                Some(d) => {
                    if tokio::time::timeout_at(d, rx.changed()).await.is_err() {
                        bail!("{what}: not within {} s", timeout.unwrap_or_default());
                    }
                }
                None => {
                    let _ = rx.changed().await;
                }
            }
        }
    }

    /// A call to a vehicle: waits for the provider (it may not be up yet), then calls;
    /// retries a lost or timed-out call, not a refusal.
    async fn call<A: marea::Payload, R: marea::Payload>(
        &self,
        f: &Function<A, R>,
        args: &A,
        what: &str,
    ) -> anyhow::Result<R> {
        let mut attempts = 0;
        loop {
            if !f.wait_provider(self.discovery_timeout).await {
                bail!("{what}: no provider within {:?}", self.discovery_timeout);
            }
            match f.call(args, self.call_timeout).await {
                Ok(r) => return Ok(r),
                Err(e @ (CallError::Remote { .. } | CallError::TypeMismatch { .. })) => {
                    return Err(anyhow!("{what}: {e}"))
                }
                Err(e) if attempts >= 5 => return Err(anyhow!("{what}: {e}")),
                Err(e) => {
                    tracing::warn!("{what}: {e}; trying again");
                    attempts += 1;
                    tokio::time::sleep(Duration::from_secs(1)).await;
                }
            }
        }
    }

    async fn set_state(&self, i: usize, to: FlightState) -> anyhow::Result<()> {
        let who = &self.plan.vehicles[i].id;
        let req = StateChangeRequest { to };
        match self
            .call(
                &self.vehicles[i].change_state,
                &req,
                &format!("{who}: change_state {to}"),
            )
            .await
        {
            Ok(_) => Ok(()),
            // The FPMa (or the autopilot) got there first: what was wanted.
            Err(e) if e.to_string().contains(&format!("already in {to}")) => Ok(()),
            Err(e) => Err(e),
        }
    }

    /// Puts the vehicle in WAYPOINT_NAVIGATION unless it is held or paused (the release does
    /// it then). A refusal is asked again a few times: the VAS refuses while the FPMa is
    /// still filling its queue.
    async fn navigate(&self, i: usize) -> anyhow::Result<()> {
        let mut attempt = 0;
        loop {
            {
                let st = self.state();
                let v = &st.vs[i];
                if v.held || v.paused || !v.wants_nav {
                    return Ok(());
                }
                if v.flight_state == Some(FlightState::WaypointNavigation) && attempt > 0 {
                    return Ok(());
                }
            }
            match self.set_state(i, FlightState::WaypointNavigation).await {
                Ok(()) => return Ok(()),
                Err(e) if attempt + 1 >= NAV_ATTEMPTS => return Err(e),
                Err(e) => {
                    tracing::debug!("{e:#}; asking again");
                    attempt += 1;
                    tokio::time::sleep(NAV_RETRY).await;
                }
            }
        }
    }

    /// Stops the vehicle where it is: a rover parks (the VAS's PARKING, the autopilot's
    /// HOLD); an aircraft, whose PARKING is a landing, holds in the air (DIRECTED: the
    /// autopilot's GUIDED, holding where it is until told more).
    async fn stop(&self, i: usize) -> anyhow::Result<()> {
        let moving = matches!(
            self.state().vs[i].flight_state,
            Some(FlightState::WaypointNavigation) | None
        );
        if moving {
            let hold = if self.plan.vehicles[i].kind == flightplan::vehicle::VehicleKind::Rover {
                FlightState::Parking
            } else {
                FlightState::Directed
            };
            self.set_state(i, hold).await?;
        }
        Ok(())
    }

    /// Loads `xml` into vehicle `i`'s FPMa, starts it, and with `wait` waits for it to
    /// complete.
    async fn fly(&self, i: usize, xml: &str, wait: bool) -> anyhow::Result<()> {
        let who = self.plan.vehicles[i].id.clone();
        let loaded = self
            .call(
                &self.vehicles[i].load_plan,
                &xml.to_owned(),
                &format!("{who}: load_plan"),
            )
            .await?;
        tracing::info!(
            "{who}: plan `{}` loaded as version {}",
            loaded.name,
            loaded.version
        );
        {
            let mut st = self.state();
            let v = &mut st.vs[i];
            v.version = Some(loaded.version);
            v.plan = Some(loaded.name.clone());
            let (route, aircraft) = route_of(xml, self.plan.vehicles[i].kind);
            v.route = route;
            v.done = false;
            v.progress = 0.0;
            v.wants_nav = true;
            v.current.clone_from(&aircraft);
            if let Some(a) = aircraft {
                match &mut v.flight {
                    Some((flight, record)) => record.next_plan(flight.then(a)),
                    None => v.flight = Some((a, FlightRecord::default())),
                }
            }
        }
        self.bump();
        // `Some` for an aircraft: whether this plan ends with a landing.
        let lands = {
            let st = self.state();
            st.vs[i].current.as_ref().map(|a| a.landing.is_some())
        };
        if lands.is_some() {
            self.take_off(i).await?;
        }
        self.navigate(i).await?;
        if wait {
            let version = loaded.version;
            self.wait_for(None, "", move |st| {
                st.vs[i].done && st.vs[i].version == Some(version)
            })
            .await?;
            tracing::info!("{who}: plan `{}` completed", loaded.name);
            if lands == Some(false) {
                // An aircraft at the end of its mission stays in it (a copter hovers at the
                // last waypoint in AUTO), where a next plan would not start: it holds there
                // (DIRECTED), as its pilot would have it, until the next plan navigates.
                self.set_state(i, FlightState::Directed).await?;
            }
            if lands == Some(true) {
                // Landed only once on the ground and disarmed (the VAS parks it then).
                self.wait_for(
                    Some(LANDING_WAIT_S),
                    &format!("{who}: landing"),
                    move |st| {
                        st.vs[i]
                            .flight
                            .as_ref()
                            .is_some_and(|(_, r)| r.parked_after_flight())
                    },
                )
                .await?;
                tracing::info!("{who}: landed and parked");
            }
        }
        Ok(())
    }

    /// An aircraft on the ground takes off before it navigates, as its pilot would: once the
    /// FPMa has queued the plan's first waypoints (the climb goes to the first one's
    /// altitude), TAKE_OFF, then wait for the climb. One already flying does nothing.
    async fn take_off(&self, i: usize) -> anyhow::Result<()> {
        let who = self.plan.vehicles[i].id.clone();
        self.wait_for(
            Some(STEP_WAIT_S),
            &format!("{who}: the VAS configured, and what it allows"),
            // Past CONFIGURE_CHECK, and what it allows from the state it is in (the two are
            // published apart).
            move |st| {
                let v = &st.vs[i];
                v.flight_state
                    .is_some_and(|s| s != FlightState::ConfigureCheck)
                    && v.allowed.as_ref().is_some_and(|a| a.from == v.flight_state)
            },
        )
        .await?;
        let due = {
            let st = self.state();
            let v = &st.vs[i];
            v.flight_state
                .and_then(|s| aircraft::start_request(s, v.allowed.as_ref(), false))
        };
        if due != Some(FlightState::TakeOff) {
            return Ok(());
        }
        self.wait_for(
            Some(STEP_WAIT_S),
            &format!("{who}: the plan's waypoints at the VAS"),
            move |st| st.vs[i].queued > 0,
        )
        .await?;
        let mut attempt = 0;
        loop {
            match self.set_state(i, FlightState::TakeOff).await {
                Ok(()) => break,
                Err(e) if attempt + 1 >= NAV_ATTEMPTS => return Err(e),
                Err(e) => {
                    tracing::debug!("{e:#}; asking again");
                    attempt += 1;
                    tokio::time::sleep(NAV_RETRY).await;
                }
            }
        }
        let to = self.state().vs[i]
            .current
            .as_ref()
            .and_then(|a| a.takeoff_alt);
        tracing::info!(
            "{who}: taking off (TAKE_OFF){}",
            to.map_or_else(String::new, |t| format!(" to {t:.0} m"))
        );
        self.wait_for(
            Some(CLIMB_WAIT_S),
            &format!("{who}: the climb"),
            move |st| {
                let v = &st.vs[i];
                match (&v.current, &v.last) {
                    (Some(a), Some(p)) => a.climbed(p),
                    _ => false,
                }
            },
        )
        .await
    }

    /// The Broz investigator: visits detections nearest first until `until` holds and none
    /// is left.
    async fn investigate(
        &self,
        i: usize,
        until: &flightplan::expr::Condition,
        speed: f64,
        alt_m: f64,
    ) -> anyhow::Result<()> {
        let keep_off = self.plan.separation.map_or(0.0, |s| s.hold_m);
        let vertical = self.plan.separation.and_then(|s| s.vertical_m);
        let mut rx = self.changed.subscribe();
        loop {
            rx.borrow_and_update();
            let choice = {
                let mut st = self.state();
                let pending: Vec<usize> = (0..st.detections.len())
                    .filter(|k| points::pending(&st.detections[*k]) && !st.claimed.contains(k))
                    .collect();
                let st = &mut *st;
                let ordered = points::Points {
                    detections: &mut st.detections,
                    visit_first: &mut st.visit_first,
                }
                .first_ordered(|k| !st.claimed.contains(&k));
                match (st.vs[i].position, ordered) {
                    (None, _) => None,
                    // The operator's order first.
                    (Some(here), Some(k)) => {
                        st.claimed.insert(k);
                        Some((k, here, (st.detections[k].lat, st.detections[k].lon)))
                    }
                    (Some(here), None) => {
                        let pts: Vec<(f64, f64)> = pending
                            .iter()
                            .map(|&k| (st.detections[k].lat, st.detections[k].lon))
                            .collect();
                        // Vehicles apart in altitude from the visits are not in the way.
                        let others: Vec<(f64, f64)> = (0..st.vs.len())
                            .filter(|&o| o != i)
                            .filter(|&o| {
                                let alt = st.vs[o].last.as_ref().map_or(0.0, |p| p.alt_rel);
                                vertical.is_none_or(|v| (alt - alt_m).abs() < v)
                            })
                            .filter_map(|o| st.vs[o].position)
                            .collect();
                        search::next_target(here, &pts, &others, keep_off).map(|j| {
                            let k = pending[j];
                            st.claimed.insert(k);
                            (k, here, pts[j])
                        })
                    }
                }
            };
            let Some((k, here, target)) = choice else {
                let finished = {
                    let st = self.state();
                    !st.detections.iter().any(points::pending) && until.holds(&|n| self.var(&st, n))
                };
                if finished {
                    let mut st = self.state();
                    st.vs[i].done = true;
                    drop(st);
                    self.bump();
                    return Ok(());
                }
                let _ = rx.changed().await;
                continue;
            };
            let id = self.state().detections[k].id;
            let far = flightplan::geo::distance(
                flightplan::geo::GeoPoint::new(here.0, here.1),
                flightplan::geo::GeoPoint::new(target.0, target.1),
            );
            tracing::info!(
                "{}: visiting detection #{id} ({far:.0} m away)",
                self.plan.vehicles[i].id
            );
            let r = if far > VISIT_RADIUS_M {
                // Round the static obstacles that reach the visits' altitude (a rover at ground
                // level: every one).
                match wavefront::route(here, target, alt_m, &self.plan.obstacles) {
                    Ok(via) => {
                        if via.len() > 1 {
                            tracing::info!(
                                "{}: detection #{id} routed round the obstacles ({} turns)",
                                self.plan.vehicles[i].id,
                                via.len() - 1
                            );
                            self.state().detours += 1;
                        }
                        self.fly(i, &visit_plan(id, here, &via, speed, alt_m), true)
                            .await
                    }
                    Err(e) => Err(anyhow!(
                        "{}: cannot reach detection #{id}: {e}",
                        self.plan.vehicles[i].id
                    )),
                }
            } else {
                Ok(())
            };
            let mut st = self.state();
            st.claimed.remove(&k);
            if r.is_ok() {
                let at = self.elapsed();
                st.detections[k].visited = Some((self.plan.vehicles[i].id.clone(), at));
                st.visit_order.push(id);
            }
            drop(st);
            self.bump();
            r?;
        }
    }

    fn exec<'a>(&'a self, b: &'a Block) -> Exec<'a> {
        Box::pin(async move {
            let label = format!("{}:{} {}", b.line, b.col, describe(&self.plan, &b.kind));
            let leaf = !matches!(
                b.kind,
                BlockKind::Seq(_)
                    | BlockKind::Par(_)
                    | BlockKind::Repeat { .. }
                    | BlockKind::If { .. }
            );
            if leaf {
                self.state().doing.push(label.clone());
                self.bump();
            }
            let r = self.exec_inner(b).await;
            if leaf {
                let mut st = self.state();
                if let Some(p) = st.doing.iter().position(|d| *d == label) {
                    st.doing.remove(p);
                }
                drop(st);
                self.bump();
            }
            r.with_context(|| format!("line {}:{} <{}>", b.line, b.col, tag(&b.kind)))
        })
    }

    async fn exec_inner(&self, b: &Block) -> anyhow::Result<()> {
        match &b.kind {
            BlockKind::Seq(body) => {
                for c in body {
                    self.exec(c).await?;
                }
            }
            BlockKind::Par(body) => {
                futures_util::future::try_join_all(body.iter().map(|c| self.exec(c))).await?;
            }
            BlockKind::Fly {
                vehicle, xml, wait, ..
            } => self.fly(*vehicle, xml, *wait).await?,
            BlockKind::Goto { vehicle, leg } => {
                let who = &self.plan.vehicles[*vehicle].id;
                self.call(
                    &self.vehicles[*vehicle].goto_leg,
                    leg,
                    &format!("{who}: goto_leg {leg}"),
                )
                .await?;
                self.state().vs[*vehicle].wants_nav = true;
                self.navigate(*vehicle).await?;
            }
            BlockKind::Pause { vehicle } => {
                self.command_pause(&self.plan.vehicles[*vehicle].id, true)
                    .await
                    .map_err(anyhow::Error::msg)?;
            }
            BlockKind::Resume { vehicle } => {
                self.command_pause(&self.plan.vehicles[*vehicle].id, false)
                    .await
                    .map_err(anyhow::Error::msg)?;
            }
            BlockKind::WaitEvent {
                event,
                vehicle,
                timeout_s,
            } => {
                let count = |st: &State| -> u64 {
                    match event {
                        WaitEvent::Detection => st
                            .detections
                            .iter()
                            .filter(|d| vehicle.is_none_or(|v| d.by == self.plan.vehicles[v].id))
                            .count() as u64,
                        WaitEvent::Completed => vehicle.map_or(0, |v| st.vs[v].completions),
                    }
                };
                let before = count(&self.state());
                self.wait_for(*timeout_s, "the event", |st| count(st) > before)
                    .await?;
            }
            BlockKind::WaitUntil { cond, timeout_s } => {
                let what = format!("`{}`", cond.src);
                self.wait_for(*timeout_s, &what, |st| cond.holds(&|n| self.var(st, n)))
                    .await?;
            }
            BlockKind::Repeat {
                count,
                while_,
                until,
                body,
            } => {
                let mut n = 0u32;
                loop {
                    if count.is_some_and(|c| n >= c) {
                        break;
                    }
                    if while_.as_ref().is_some_and(|w| !self.holds(w)) {
                        break;
                    }
                    for c in body {
                        self.exec(c).await?;
                    }
                    n += 1;
                    if until.as_ref().is_some_and(|u| self.holds(u)) {
                        break;
                    }
                    // A loop whose body never waits must not starve the runtime.
                    tokio::task::yield_now().await;
                }
            }
            BlockKind::If { cond, then, else_ } => {
                let body = if self.holds(cond) { then } else { else_ };
                for c in body {
                    self.exec(c).await?;
                }
            }
            BlockKind::Sync { name, parties } => {
                let gen = {
                    let mut st = self.state();
                    let e = st.barriers.entry(name.clone()).or_default();
                    e.0 += 1;
                    if e.0 >= *parties {
                        e.0 = 0;
                        e.1 += 1;
                        None
                    } else {
                        Some(e.1)
                    }
                };
                match gen {
                    None => {
                        tracing::info!("sync point `{name}`: all {parties} there, going on");
                        self.bump();
                    }
                    Some(g) => {
                        self.wait_for(None, "", |st| {
                            st.barriers.get(name).is_some_and(|e| e.1 != g)
                        })
                        .await?;
                    }
                }
            }
            BlockKind::Set { var, expr, add } => {
                let mut st = self.state();
                let v = match (expr, add) {
                    (Some(expr), _) => expr.eval(&|n| self.var(&st, n)),
                    (None, Some(x)) => match st.vars.get(var) {
                        Some(Value::Number(n)) => Value::Number(n + x),
                        _ => bail!("`{var}` is not a number"),
                    },
                    (None, None) => bail!("nothing to set `{var}` to"),
                };
                st.vars.insert(var.clone(), v);
                drop(st);
                self.bump();
            }
            BlockKind::Investigate {
                vehicle,
                until,
                speed,
                alt_m,
            } => self.investigate(*vehicle, until, *speed, *alt_m).await?,
            BlockKind::Log { text } => tracing::info!("{text}"),
        }
        Ok(())
    }

    /// `pause` / `resume` of a vehicle, by command or by the plan.
    /// An operator's edit of the points to visit ([`points`]).
    fn edit_points(&self, edit: flightplan::fleet_api::PointEdit) -> Result<String, String> {
        let at_s = self.elapsed();
        let said = {
            let mut st = self.state();
            let st = &mut *st;
            points::Points {
                detections: &mut st.detections,
                visit_first: &mut st.visit_first,
            }
            .apply(edit, &self.plan.obstacles, &st.claimed, at_s)
        };
        match &said {
            Ok(text) => {
                tracing::info!("operator: {text}");
                self.bump();
            }
            // Nothing changed: nobody to wake.
            Err(e) => tracing::warn!("operator's point edit refused: {e}"),
        }
        said
    }

    async fn command_pause(&self, id: &str, pause: bool) -> Result<String, String> {
        let i = self
            .plan
            .vehicle(id)
            .ok_or_else(|| format!("no vehicle `{id}` in the fleet plan"))?;
        self.state().vs[i].paused = pause;
        self.bump();
        if pause {
            self.stop(i).await.map_err(|e| format!("{e:#}"))?;
            Ok(format!("{id} paused"))
        } else {
            self.navigate(i).await.map_err(|e| format!("{e:#}"))?;
            Ok(format!("{id} resumed"))
        }
    }

    /// Separation actions, carried out in order.
    async fn separate(&self, actions: Vec<Action>) {
        for a in actions {
            let r = match a {
                Action::Hold(i) => {
                    tracing::warn!("separation: {} holds", self.plan.vehicles[i].id);
                    self.state().vs[i].held = true;
                    self.stop(i).await
                }
                Action::Release(i) => {
                    tracing::info!("separation: {} clear, going on", self.plan.vehicles[i].id);
                    self.state().vs[i].held = false;
                    self.navigate(i).await
                }
            };
            self.bump();
            if let Err(e) = r {
                tracing::error!("separation: {e:#}");
            }
        }
    }

    /// The subscriptions to every vehicle's position, state, progress, plan events, detections,
    /// allowed changes and queue.
    fn watch_vehicles(
        self: &Arc<Self>,
        tasks: &TaskTracker,
        stop: &CancellationToken,
    ) -> anyhow::Result<()> {
        for (i, v) in self.plan.vehicles.iter().enumerate() {
            let (fpma_at, vas_at) = (format!("{}/fpma", v.prefix), format!("{}/vas", v.prefix));
            let position = vas::POSITION.subscribe(&self.svc, &vas_at)?;
            let state = vas::FLIGHT_STATE.subscribe(&self.svc, &vas_at)?;
            let progress = fpma::PROGRESS.subscribe(&self.svc, &fpma_at)?;
            let plan_events = fpma::PLAN_EVENT.subscribe(&self.svc, &fpma_at)?;
            let detections = vas::DETECTION.subscribe(&self.svc, &vas_at)?;
            let allowed = vas::ALLOWED_CHANGES.subscribe(&self.svc, &vas_at)?;
            let queue = vas::QUEUE.subscribe(&self.svc, &vas_at)?;
            let me = self.clone();
            let stop = stop.clone();
            let id = v.id.clone();
            tasks.spawn(async move {
                loop {
                    tokio::select! {
                        () = stop.cancelled() => return,
                        p = position.recv() => {
                            let p = match p {
                                Ok(x) => x,
                                Err(marea::RecvError::Closed) => return,
                                Err(e) => { tracing::warn!("{id}: {e}"); continue }
                            };
                            let actions = {
                                let mut st = me.state();
                                st.vs[i].position = Some((p.value.lat, p.value.lon));
                                let v = &mut st.vs[i];
                                if let Some((plan, record)) = &mut v.flight {
                                    record.position(plan, &p.value);
                                }
                                v.last = Some(p.value);
                                // An obstacle entered below its top: counted once per entry.
                                let inside = me
                                    .plan
                                    .obstacles
                                    .iter()
                                    .find(|o| {
                                        p.value.alt_rel < o.height_m
                                            && wavefront::contains(o, (p.value.lat, p.value.lon))
                                    })
                                    .map(|o| o.name.clone());
                                if inside.is_some() && st.vs[i].inside.is_none() {
                                    tracing::error!(
                                        "{id} entered obstacle `{}`",
                                        inside.as_deref().unwrap_or_default()
                                    );
                                    st.obstacle_entries += 1;
                                }
                                st.vs[i].inside = inside;
                                st.monitor
                                    .as_mut()
                                    .map(|m| m.update(i, p.value.lat, p.value.lon, p.value.alt_rel))
                                    .unwrap_or_default()
                            };
                            me.bump();
                            if !actions.is_empty() {
                                me.separate(actions).await;
                            }
                        }
                        s = state.recv() => {
                            let s = match s {
                                Ok(x) => x,
                                Err(marea::RecvError::Closed) => return,
                                Err(e) => { tracing::warn!("{id}: {e}"); continue }
                            };
                            let mut st = me.state();
                            let v = &mut st.vs[i];
                            v.flight_state = Some(s.value);
                            if let Some((_, record)) = &mut v.flight {
                                record.state(s.value, v.last.as_ref());
                            }
                            drop(st);
                            me.bump();
                        }
                        a = allowed.recv() => {
                            let a = match a {
                                Ok(x) => x,
                                Err(marea::RecvError::Closed) => return,
                                Err(e) => { tracing::warn!("{id}: {e}"); continue }
                            };
                            me.state().vs[i].allowed = Some(a.value);
                            me.bump();
                        }
                        q = queue.recv() => {
                            let q = match q {
                                Ok(x) => x,
                                Err(marea::RecvError::Closed) => return,
                                Err(e) => { tracing::warn!("{id}: {e}"); continue }
                            };
                            me.state().vs[i].queued = q.value.queued;
                            me.bump();
                        }
                        p = progress.recv() => {
                            let p = match p {
                                Ok(x) => x,
                                Err(marea::RecvError::Closed) => return,
                                Err(e) => { tracing::warn!("{id}: {e}"); continue }
                            };
                            let p = p.value;
                            let mut st = me.state();
                            let v = &mut st.vs[i];
                            if v.version == Some(p.version) {
                                v.progress = p.fraction;
                                if p.completed && !v.done {
                                    v.done = true;
                                    v.wants_nav = false;
                                    v.completions += 1;
                                }
                            }
                            drop(st);
                            me.bump();
                        }
                        e = plan_events.recv() => {
                            let e = match e {
                                Ok(x) => x.value,
                                Err(marea::RecvError::Closed) => return,
                                Err(e) => { tracing::warn!("{id}: {e}"); continue }
                            };
                            let mut st = me.state();
                            let v = &mut st.vs[i];
                            if let (Some((plan, record)), PlanEventKind::WaypointReached { leg, .. }) =
                                (&mut v.flight, &e.kind)
                            {
                                if v.version == Some(e.version) {
                                    record.reached(plan, leg, v.last.as_ref());
                                }
                            }
                        }
                        d = detections.recv() => {
                            let d = match d {
                                Ok(x) => x.value,
                                Err(marea::RecvError::Closed) => return,
                                Err(e) => { tracing::warn!("{id}: {e}"); continue }
                            };
                            let mut st = me.state();
                            if !st.detections.iter().any(|x| x.id == d.id && x.by == id) {
                                tracing::info!(
                                    "{id} detected #{} at {:.7},{:.7} ({:.0} % sure)",
                                    d.id, d.lat, d.lon, d.confidence * 100.0
                                );
                                let at_s = me.elapsed();
                                st.detections.push(Detection {
                                    id: d.id, by: id.clone(), lat: d.lat, lon: d.lon,
                                    confidence: d.confidence, at_s, visited: None,
                                    deleted: false,
                                });
                            }
                            drop(st);
                            me.bump();
                        }
                    }
                }
            });
        }
        Ok(())
    }

    fn status(&self) -> FleetStatus {
        let st = self.state();
        FleetStatus {
            plan: self.plan.name.clone(),
            elapsed_s: st.ended.unwrap_or_else(|| self.elapsed()),
            done: st.done,
            failed: st.failed.clone(),
            doing: st.doing.clone(),
            vehicles: self
                .plan
                .vehicles
                .iter()
                .zip(&st.vs)
                .map(|(d, v)| VehicleStatus {
                    id: d.id.clone(),
                    prefix: d.prefix.clone(),
                    priority: d.priority,
                    state: v.flight_state.map(|s| s.to_string()),
                    position: v.position,
                    plan: v.plan.clone(),
                    progress: v.progress,
                    done: v.done,
                    holding: v.held,
                    paused: v.paused,
                    route: v.route.clone(),
                    aircraft: v.flight.as_ref().map(|(plan, r)| r.summary(plan)),
                })
                .collect(),
            detections: st.detections.clone(),
            visit_order: st.visit_order.clone(),
            separation: {
                let mut s = st
                    .monitor
                    .as_ref()
                    .map(|m| m.status().clone())
                    .unwrap_or_default();
                s.obstacle_entries = st.obstacle_entries;
                s.detours = st.detours;
                s
            },
            vars: self
                .plan
                .vars
                .iter()
                .filter_map(|(n, _)| st.vars.get(n).map(|v| (n.clone(), (*v).into())))
                .collect(),
            obstacles: self
                .plan
                .obstacles
                .iter()
                .map(|o| flightplan::fleet_api::ObstacleView {
                    name: o.name.clone(),
                    height_m: o.height_m,
                    polygon: o.polygon.clone(),
                })
                .collect(),
            visit_first: st.visit_first.clone(),
        }
    }

    async fn publish_status(&self, var: marea::Variable<FleetStatus>, stop: CancellationToken) {
        let mut rx = self.changed.subscribe();
        loop {
            if let Err(e) = var.set(&self.status()) {
                tracing::warn!("publishing the status: {e}");
            }
            tokio::select! {
                () = stop.cancelled() => return,
                _ = tokio::time::sleep(STATUS_PERIOD) => {}
                r = rx.changed() => {
                    if r.is_err() { return }
                    tokio::select! {
                        () = stop.cancelled() => return,
                        () = tokio::time::sleep(STATUS_MIN_PERIOD) => {}
                    }
                }
            }
        }
    }
}

/// The nominal waypoints of a flight plan (already checked when the fleet plan was loaded, or
/// generated), thinned for the status; empty if it cannot be expanded.
/// A plan's route for the maps and, for an aircraft, its take-off, altitudes and landing.
fn route_of(
    xml: &str,
    kind: flightplan::vehicle::VehicleKind,
) -> (Vec<(f64, f64)>, Option<AircraftPlan>) {
    let params = flightplan::vehicle::VehicleParams::for_kind(kind);
    let Ok(plan) = flightplan::check::load(xml, &params) else {
        return (Vec::new(), None);
    };
    let wps = plan.nominal();
    let pts: Vec<(f64, f64)> = wps.iter().map(|w| (w.lat, w.lon)).collect();
    let aircraft = (kind != flightplan::vehicle::VehicleKind::Rover)
        .then(|| AircraftPlan::of(plan.plan().altitude_reference(), wps));
    (
        flightplan::fleet_api::thin(&pts, flightplan::fleet_api::ROUTE_POINTS),
        aircraft,
    )
}

/// The flight plan of one visit: from where the vehicle is to the detection, fly-over.
/// The route is `via` (the wavefront planner's turns, the detection last), fly-over at the
/// detection, at `alt` metres above home (0 for a rover).
pub fn visit_plan(id: u32, from: (f64, f64), via: &[(f64, f64)], speed: f64, alt: f64) -> String {
    let mut fixes = format!(
        r#"    <fix id="HERE" lat="{:.8}" lon="{:.8}" alt="{alt}"/>"#,
        from.0, from.1
    );
    let mut legs = String::from(r#"    <leg type="IF" fix="HERE"/>"#);
    for (k, p) in via.iter().enumerate() {
        let last = k + 1 == via.len();
        let fix = if last {
            "POI".to_owned()
        } else {
            format!("T{k}")
        };
        fixes.push_str(&format!(
            "\n    <fix id=\"{fix}\" lat=\"{:.8}\" lon=\"{:.8}\" alt=\"{alt}\"/>",
            p.0, p.1
        ));
        legs.push_str(&format!(
            "\n    <leg type=\"TF\" fix=\"{fix}\"{}/>",
            if last { " flyOver=\"true\"" } else { "" }
        ));
    }
    format!(
        r#"<flightPlan name="visit-{id}" version="1" altRef="REL" defaultSpeed="{speed}">
  <fixes>
{fixes}
  </fixes>
  <mission>
{legs}
  </mission>
</flightPlan>"#
    )
}

fn tag(k: &BlockKind) -> &'static str {
    match k {
        BlockKind::Seq(_) => "seq",
        BlockKind::Par(_) => "par",
        BlockKind::Fly { .. } => "fly",
        BlockKind::Goto { .. } => "goto",
        BlockKind::Pause { .. } => "pause",
        BlockKind::Resume { .. } => "resume",
        BlockKind::WaitEvent { .. } | BlockKind::WaitUntil { .. } => "wait",
        BlockKind::Repeat { .. } => "repeat",
        BlockKind::If { .. } => "if",
        BlockKind::Sync { .. } => "sync",
        BlockKind::Set { .. } => "set",
        BlockKind::Investigate { .. } => "investigate",
        BlockKind::Log { .. } => "log",
    }
}

/// A statement in a few words, for the status's `doing`.
fn describe(plan: &FleetPlan, k: &BlockKind) -> String {
    let v = |i: &usize| plan.vehicles[*i].id.as_str();
    match k {
        BlockKind::Fly { vehicle, file, .. } => format!(
            "fly {} {}",
            v(vehicle),
            file.file_name()
                .map_or_else(String::new, |f| f.to_string_lossy().into_owned())
        ),
        BlockKind::Goto { vehicle, leg } => format!("goto {} {leg}", v(vehicle)),
        BlockKind::Pause { vehicle } => format!("pause {}", v(vehicle)),
        BlockKind::Resume { vehicle } => format!("resume {}", v(vehicle)),
        BlockKind::WaitUntil { cond, .. } => format!("wait until {}", cond.src),
        BlockKind::WaitEvent { event, .. } => format!("wait for {event:?}"),
        BlockKind::Sync { name, .. } => format!("sync {name}"),
        BlockKind::Investigate { vehicle, .. } => format!("investigate {}", v(vehicle)),
        other => tag(other).to_owned(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_visit_plan_is_a_valid_rover_plan_to_the_point() {
        let xml = visit_plan(3, (41.2752, 1.9875), &[(41.2756, 1.9872)], 3.0, 0.0);
        let params = flightplan::vehicle::VehicleParams::rover();
        let plan = flightplan::check::load(&xml, &params).unwrap();
        let last = plan.nominal().last().unwrap();
        assert!((last.lat - 41.2756).abs() < 1e-7 && (last.lon - 1.9872).abs() < 1e-7);
        assert!(last.fly_over);
        // Round an obstacle: through each turn, the detection last.
        let via = [(41.2753, 1.9876), (41.2755, 1.9874), (41.2756, 1.9872)];
        let xml = visit_plan(4, (41.2752, 1.9875), &via, 3.0, 0.0);
        let plan = flightplan::check::load(&xml, &params).unwrap();
        let n = plan.nominal();
        for p in via {
            assert!(
                n.iter()
                    .any(|w| (w.lat - p.0).abs() < 1e-7 && (w.lon - p.1).abs() < 1e-7),
                "{p:?} not flown: {xml}"
            );
        }
        assert!(n.last().unwrap().fly_over);
        // An aircraft's visit, at its altitude.
        let xml = visit_plan(5, (41.2752, 1.9875), &[(41.2756, 1.9872)], 3.0, 12.0);
        let copter =
            flightplan::vehicle::VehicleParams::for_kind(flightplan::vehicle::VehicleKind::Copter);
        let plan = flightplan::check::load(&xml, &copter).unwrap();
        assert!(plan.nominal().iter().all(|w| w.alt == 12.0), "{xml}");
    }

    #[test]
    fn routes_are_thinned_with_their_ends_kept() {
        let pts: Vec<(f64, f64)> = (0..1000).map(|i| (f64::from(i), 0.0)).collect();
        let t = flightplan::fleet_api::thin(&pts, 300);
        assert_eq!(t.len(), 300);
        assert_eq!((t[0].0, t[299].0), (0.0, 999.0));
        assert_eq!(flightplan::fleet_api::thin(&pts[..5], 300).len(), 5);
        let r = route_of(
            &visit_plan(1, (41.2752, 1.9875), &[(41.2756, 1.9872)], 3.0, 0.0),
            flightplan::vehicle::VehicleKind::Rover,
        );
        assert_eq!(r.0.len(), 2);
        assert!(r.1.is_none(), "a rover has no aircraft plan");
        assert!(route_of("<nope/>", flightplan::vehicle::VehicleKind::Rover)
            .0
            .is_empty());
    }
}
