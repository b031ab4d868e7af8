//! The USAL Flight Monitor (FMo, 003 §1.2, §6.2.5): the pilot's ground station, served as one web
//! page from the station's machine so any laptop or tablet browser is the screen.
//!
//! Layers: [`model`] is the station's picture of the fleet (pure, tested on a fake clock);
//! [`web`] serves the page, its JSON API and its live channel (server-sent events), on the
//! plumbing every station shares (`station_web`: options, startup, the common routes, the live
//! channel, the command log); this file
//! opens the middleware node, subscribes to what the page shows (and nothing else: 003 §6.2.4),
//! calls the VAS's functions and publishes `fmo/manual_control` (addressed to the commanded
//! vehicle only) at 20 Hz while the dead-man is held. Items and options are listed in `services/fmo/README.md`.
//!
//! ```no_run
//! # async fn f() -> anyhow::Result<()> {
//! let shutdown = tokio_util::sync::CancellationToken::new();
//! let mut config = fmo::FmoConfig::default();
//! config.station.listen = "127.0.0.1:0".parse()?;
//! fmo::run(config, shutdown).await // prints FMO_URL=http://127.0.0.1:PORT/?token=TOKEN
//! # }
//! ```

pub mod model;
mod others;
pub mod web;

use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use anyhow::Context;
use flightplan::api::items as fpma;
use marea::{Function, FunctionItem, Service, VariableSubscriber};
use station_web::{call_error, Live, StationConfig};
use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;
use usal_types::items::{fmo, station, vas};
use usal_types::{
    CommandReply, FlightState, ParamValue, StateChangeReply, StateChangeRequest, VehicleCommand,
};

use crate::model::{Item, ManualTick, Station};

/// Everything the FMo needs.
#[derive(Clone, Debug)]
pub struct FmoConfig {
    /// What every station needs: network, node, HTTP address, staleness, call time limit.
    pub station: StationConfig,
    /// The VASes followed: a pattern of their item prefix (`**/vas` for a fleet, `rover1/vas`
    /// for one vehicle).
    pub vas: String,
}

impl Default for FmoConfig {
    fn default() -> Self {
        Self {
            station: StationConfig::new("fmo", 8081),
            vas: "**/vas".into(),
        }
    }
}

/// Manual-control publication rate (003 §6.2.5: the seed's joystick rate).
const MANUAL_PERIOD: Duration = Duration::from_millis(50);
/// How often the allowed transitions of the commanded vehicle are asked again while the last
/// answer is missing, outdated or failed.
const ALLOWED_RETRY: Duration = Duration::from_secs(2);

type ChangeStateFn = Function<StateChangeRequest, StateChangeReply>;
type AllowedFn = Function<(), Vec<FlightState>>;
type CommandFn = Function<VehicleCommand, CommandReply>;
type ListParamsFn = Function<(), Vec<ParamValue>>;
type SetParamFn = Function<ParamValue, ParamValue>;
/// The function handles of the vehicles called so far, by full name.
type FunctionCache<A, R> = Mutex<HashMap<String, Arc<Function<A, R>>>>;

/// What the HTTP handlers and the middleware tasks share.
pub struct Shared {
    station: Mutex<Station>,
    svc: Service,
    /// Change notification, cancellation and tasks.
    pub live: Live,
    /// Woken when the commanded vehicle's allowed transitions must be asked again.
    refresh_allowed: Notify,
    change_state: Mutex<HashMap<String, Arc<ChangeStateFn>>>,
    allowed: Mutex<HashMap<String, Arc<AllowedFn>>>,
    command: Mutex<HashMap<String, Arc<CommandFn>>>,
    list_params: Mutex<HashMap<String, Arc<ListParamsFn>>>,
    set_param: Mutex<HashMap<String, Arc<SetParamFn>>>,
    call_timeout: Duration,
    /// A flight log being played back (`usal replay`), shown as a REPLAY.
    pub replay: station_web::replay::ReplayWatch,
    /// The map's tiles, if any.
    pub tiles: Option<Arc<station_web::tiles::Tiles>>,
}

impl Shared {
    /// The station state. A panic while holding the lock cannot leave it inconsistent in a way
    /// worth stopping the station for, so a poisoned lock is taken over.
    pub fn station(&self) -> MutexGuard<'_, Station> {
        marea::sync::lock(&self.station)
    }

    /// The handle of `vehicle`'s (a VAS prefix) function `item`, from `cache` once made.
    fn function<A: marea::Payload, R: marea::Payload>(
        &self,
        cache: &FunctionCache<A, R>,
        item: FunctionItem<A, R>,
        vehicle: &str,
    ) -> Result<Arc<Function<A, R>>, String> {
        let name = item.at(vehicle);
        let mut map = marea::sync::lock(cache);
        if let Some(f) = map.get(&name) {
            return Ok(f.clone());
        }
        let f = item
            .function(&self.svc, vehicle)
            .map_err(|e| e.to_string())?;
        let f = Arc::new(f);
        map.insert(name, f.clone());
        Ok(f)
    }

    /// Asks `vehicle` (a VAS prefix) for `to` in the background; returns the command's id. The
    /// command shows as pending until the VAS answers or the call fails.
    pub fn request_state(self: &Arc<Self>, vehicle: &str, to: FlightState) -> u64 {
        self.call_vehicle(
            vehicle,
            format!("change_state {to}"),
            |me| &me.change_state,
            vas::CHANGE_STATE,
            StateChangeRequest { to },
            |r: StateChangeReply| format!("{} → {}", r.from, r.to),
        )
    }

    /// Sends `cmd` (ARM, DISARM, DIRECTED with its altitude, speed and bearing) to `vehicle`
    /// (a VAS prefix) in the background; returns the command's id. It shows as pending until
    /// the VAS answers; a refusal carries the VAS's reason.
    pub fn send_command(self: &Arc<Self>, vehicle: &str, cmd: VehicleCommand) -> u64 {
        self.call_vehicle(
            vehicle,
            format!("command {}", describe(&cmd)),
            |me| &me.command,
            vas::COMMAND,
            cmd,
            |r: CommandReply| format!("{} done, now {}", r.command, r.state),
        )
    }

    /// The autopilot parameters of `vehicle` (a VAS prefix), as its VAS lists them now.
    ///
    /// # Errors
    /// The VAS cannot be reached or cannot list them, in words.
    pub async fn params(&self, vehicle: &str) -> Result<Vec<ParamValue>, String> {
        let f = self.function(&self.list_params, vas::LIST_PARAMS, vehicle)?;
        tokio::select! {
            r = f.call(&(), self.call_timeout) => r.map_err(call_error),
            _ = self.live.cancel.cancelled() => Err("station stopping".to_string()),
        }
    }

    /// Sets the autopilot parameter `p` of `vehicle` (a VAS prefix) in the background; returns
    /// the command's id. It shows as pending until the VAS answers with the value the
    /// autopilot took, or with why it did not.
    pub fn set_param(self: &Arc<Self>, vehicle: &str, p: ParamValue) -> u64 {
        self.call_vehicle(
            vehicle,
            format!("set_param {} = {}", p.name, p.value),
            |me| &me.set_param,
            vas::SET_PARAM,
            p,
            |r: ParamValue| format!("{} is {}", r.name, r.value),
        )
    }

    /// Calls `vehicle`'s function `item` with `arg` in the background, listed in the command
    /// log as `what` (pending until the answer, then `answered(reply)` or the failure); the
    /// allowed transitions are asked again after it. Returns the command's id.
    fn call_vehicle<A: marea::Payload, R: marea::Payload>(
        self: &Arc<Self>,
        vehicle: &str,
        what: String,
        cache: fn(&Shared) -> &FunctionCache<A, R>,
        item: FunctionItem<A, R>,
        arg: A,
        answered: fn(R) -> String,
    ) -> u64 {
        let id = self
            .station()
            .command_started(vehicle, &what, Instant::now());
        self.live.changed.notify_waiters();
        let me = self.clone();
        let vehicle = vehicle.to_owned();
        self.live.tasks.spawn(async move {
            let outcome = async {
                let f = me.function(cache(&me), item, &vehicle)?;
                tokio::select! {
                    r = f.call(&arg, me.call_timeout) => r.map_err(call_error),
                    _ = me.live.cancel.cancelled() => Err("station stopping".to_string()),
                }
            }
            .await
            .map(answered);
            me.station().command_finished(id, outcome, Instant::now());
            me.refresh_allowed.notify_one();
            me.live.changed.notify_waiters();
        });
        id
    }

    /// Asks for the commanded vehicle's allowed transitions again.
    pub fn refresh_allowed(&self) {
        self.refresh_allowed.notify_one();
    }
}

/// A command as the command list shows it: DIRECTED with its target.
fn describe(cmd: &VehicleCommand) -> String {
    match cmd {
        VehicleCommand::Directed(t) => format!(
            "DIRECTED alt {} m, {} m/s, bearing {}°",
            t.alt, t.speed, t.bearing
        ),
        other => other.to_string(),
    }
}

fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map(|d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
        .unwrap_or(0)
}

/// Follows every VAS item `item` matching the configured pattern, feeding the station.
fn follow<T: marea::Payload>(
    shared: &Arc<Shared>,
    sub: VariableSubscriber<T>,
    item: &'static str,
    to_item: fn(T) -> Item,
) {
    let me = shared.clone();
    let suffix = format!("/{item}");
    shared.live.follow(sub, item, move |s| {
        let Some(prefix) = s.name.strip_suffix(&suffix) else {
            return;
        };
        let state_changed =
            me.station()
                .update(prefix, &s.publisher, to_item(s.value), Instant::now());
        if state_changed {
            me.refresh_allowed.notify_one();
            me.live.changed.notify_waiters();
        }
        if item == vas::ALARM.name() || item == vas::STATE_CHANGED.name() {
            me.live.changed.notify_waiters();
        }
    });
}

/// Follows what the map and the instruments show beside each VAS (`NS/vas`): its FPMa's
/// progress (the ETA) and plan (the route drawn), and its nodes' link health (`NS/link/*/stats`).
fn follow_vehicle_extras(shared: &Arc<Shared>, svc: &Service, vas: &str) -> anyhow::Result<()> {
    let Some(ns_pattern) = vas.strip_suffix("vas") else {
        return Ok(());
    };
    let fpmas = format!("{ns_pattern}fpma");
    let sub = fpma::PROGRESS.subscribe(svc, &fpmas)?;
    let me = shared.clone();
    let suffix = fpma::PROGRESS.at("fpma");
    shared.live.follow(sub, "progress", move |s| {
        let Some(ns) = s.name.strip_suffix(&suffix) else {
            return;
        };
        let vehicle = format!("{ns}vas");
        me.station().update_plan(&vehicle, s.value, Instant::now());
    });
    let sub = fpma::PLAN.subscribe(svc, &fpmas)?;
    let me = shared.clone();
    let suffix = fpma::PLAN.at("fpma");
    shared.live.follow(sub, "plan", move |s| {
        let Some(ns) = s.name.strip_suffix(&suffix) else {
            return;
        };
        me.station().update_route(&format!("{ns}vas"), &s.value);
        me.live.changed.notify_waiters();
    });
    let sub = svc.subscribe_variable::<marea::LinkHealth>(&format!("{ns_pattern}link/*/stats"))?;
    let me = shared.clone();
    shared.live.follow(sub, "link health", move |s| {
        // `NS/link/NAME/stats` → the vehicle `NS/vas`.
        let Some((ns, _)) = s.name.rsplit_once("link/") else {
            return;
        };
        me.station()
            .update_link(&format!("{ns}vas"), s.value, Instant::now());
    });
    Ok(())
}

/// Keeps the commanded vehicle's allowed transitions current.
async fn allowed_loop(me: Arc<Shared>) {
    loop {
        tokio::select! {
            _ = me.refresh_allowed.notified() => {}
            _ = tokio::time::sleep(ALLOWED_RETRY) => {}
            _ = me.live.cancel.cancelled() => return,
        }
        let (vehicle, state) = {
            let st = me.station();
            let Some(v) = st.selected().map(str::to_owned) else {
                continue;
            };
            if !st.allowed_outdated(&v) {
                continue;
            }
            let s = st.flight_state(&v);
            (v, s)
        };
        let answer = match me.function(&me.allowed, vas::ALLOWED_STATES, &vehicle) {
            Ok(f) => tokio::select! {
                r = f.call(&(), me.call_timeout) => r.map_err(call_error),
                _ = me.live.cancel.cancelled() => return,
            },
            Err(e) => Err(e),
        };
        me.station()
            .set_allowed(&vehicle, state, answer, Instant::now());
        me.live.changed.notify_waiters();
    }
}

/// Publishes the sticks at 20 Hz while the dead-man is held (then neutral briefly).
async fn manual_loop(me: Arc<Shared>, var: marea::Variable<usal_types::ManualCommand>) {
    let mut tick = tokio::time::interval(MANUAL_PERIOD);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = me.live.cancel.cancelled() => return,
        }
        let t = me.station().manual_tick(Instant::now(), unix_ms());
        if let ManualTick::Send(sample) = t {
            if let Err(e) = var.set(&sample) {
                tracing::warn!("manual_control: {e}");
            }
        }
    }
}

/// Runs the FMo until `shutdown` is cancelled: binds the HTTP server, prints
/// `FMO_URL=http://ADDR/?token=TOKEN` on stdout, opens the node, then serves.
///
/// # Errors
/// The address cannot be bound, bad network file or pattern, a node that cannot open.
pub async fn run(config: FmoConfig, shutdown: CancellationToken) -> anyhow::Result<()> {
    let tiles = config.station.open_tiles()?;
    let (listener, addr) = station_web::bind(config.station.listen, "FMO_URL").await?;
    let node = station_web::open_node(&config.station).await?;
    let svc = node.service("fmo").context("declaring the fmo service")?;
    let cancel = shutdown.child_token();
    let shared = Arc::new(Shared {
        station: Mutex::new(Station::new(config.station.stale_after, Instant::now())),
        svc: svc.clone(),
        refresh_allowed: Notify::new(),
        change_state: Mutex::new(HashMap::new()),
        allowed: Mutex::new(HashMap::new()),
        command: Mutex::new(HashMap::new()),
        list_params: Mutex::new(HashMap::new()),
        set_param: Mutex::new(HashMap::new()),
        replay: station_web::replay::ReplayWatch::default(),
        tiles,
        call_timeout: config.station.call_timeout,
        live: Live::new(cancel.clone()),
    });
    let vases = config.vas.as_str();
    follow(
        &shared,
        vas::POSITION.subscribe(&svc, vases)?,
        vas::POSITION.name(),
        Item::Position,
    );
    follow(
        &shared,
        vas::ATTITUDE.subscribe(&svc, vases)?,
        vas::ATTITUDE.name(),
        Item::Attitude,
    );
    follow(
        &shared,
        vas::SPEEDS.subscribe(&svc, vases)?,
        vas::SPEEDS.name(),
        Item::Speeds,
    );
    follow(
        &shared,
        vas::AUTOPILOT.subscribe(&svc, vases)?,
        vas::AUTOPILOT.name(),
        Item::Autopilot,
    );
    follow(
        &shared,
        vas::FLIGHT_STATE.subscribe(&svc, vases)?,
        vas::FLIGHT_STATE.name(),
        Item::FlightState,
    );
    follow(
        &shared,
        vas::MISSION_TIME.subscribe(&svc, vases)?,
        vas::MISSION_TIME.name(),
        Item::MissionTime,
    );
    follow(
        &shared,
        vas::STATE_CHANGED.subscribe(&svc, vases)?,
        vas::STATE_CHANGED.name(),
        Item::StateChanged,
    );
    follow(
        &shared,
        vas::ALARM.subscribe(&svc, vases)?,
        vas::ALARM.name(),
        Item::Alarm,
    );
    follow(
        &shared,
        vas::BATTERY.subscribe(&svc, vases)?,
        vas::BATTERY.name(),
        Item::Battery,
    );
    follow(
        &shared,
        vas::HOME.subscribe(&svc, vases)?,
        vas::HOME.name(),
        Item::Home,
    );
    follow(
        &shared,
        vas::FENCE.subscribe(&svc, vases)?,
        vas::FENCE.name(),
        Item::Fence,
    );
    follow_vehicle_extras(&shared, &svc, vases)?;
    let manual = fmo::MANUAL_CONTROL.publish(&svc)?;
    // The VAS knows its ground station is there by this heartbeat (lost ground link, `vas`
    // `linkLossAction`); the FMo is the pilot's station.
    let beat = station::HEARTBEAT.publish(&svc)?;
    let station = svc.full_name("").trim_end_matches('/').to_owned();
    let stop = cancel.clone();
    shared.live.tasks.spawn(async move {
        let mut tick = tokio::time::interval(std::time::Duration::from_millis(250));
        for seq in 0.. {
            tokio::select! {
                () = stop.cancelled() => return,
                _ = tick.tick() => {
                    let _ = beat.set(&usal_types::StationHeartbeat { station: station.clone(), seq });
                }
            }
        }
    });
    shared.replay.follow(&svc, &shared.live)?;
    shared.live.tasks.spawn(allowed_loop(shared.clone()));
    shared.live.tasks.spawn(manual_loop(shared.clone(), manual));
    shared
        .live
        .tasks
        .spawn(others::follow_other_services(shared.clone()));
    tracing::info!("fmo up on http://{addr}/, following {vases}");

    // The fleet view: every vehicle of a fleet mission on one map, `/fleet`.
    let fleet_view =
        station_web::fleet::FleetView::start(&svc, &shared.live, config.station.call_timeout)?;
    // The vehicles' cameras: the latest picture, and a point marked on it sent to the fleet.
    let camera_view =
        station_web::camera::CameraView::start(&svc, &shared.live, fleet_view.clone())?;
    let router = web::router(shared.clone())
        .merge(station_web::fleet::router(fleet_view))
        .merge(station_web::camera::router(camera_view));
    let tasks = shared.live.tasks.clone();
    station_web::serve_and_shut_down(listener, router, cancel, tasks, (shared, svc), node).await
}
