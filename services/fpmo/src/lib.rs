//! The USAL Flight Plan Monitor (FPMo, 003 §1.2, §6.2.4): the flight-plan ground station, served
//! as one web page. Upload a plan (file transfer to the FPMa's `plans` sink), follow its legs and
//! progress on a map drawn to scale, skip / go to a leg, pause / resume, change a leg's
//! parameters, re-task by clicking the map, hold here / exit the hold, go to a stage, set a plan
//! variable, fire an emergency rule.
//!
//! Unlike the seed's FPMo it subscribes only to what it shows (the FPMa's `progress`, `plan`,
//! `state`, `plan_event`, `plan_rejected` and the VAS's `position`), measures in the units the user picks,
//! zooms to metres, and shows every command as pending until the FPMa answers. The plan drawn is
//! the FPMa's own (its `plan` variable, asked again with `plan_geometry` when the drawing lags
//! the progress), so any station draws any plan, whoever uploaded it ([`plan`]). Items and
//! options: `README.md`.
//!
//! Layers: [`state`] is the station's picture of the vehicles (no I/O); [`plan`] checks uploads
//! and draws plans; [`web`] the page's own routes; [`background`] the map's image; this file
//! opens the node, feeds the state from the subscriptions and calls the FPMa. What every station
//! shares (options, startup, the page / snapshot / live-channel routes, the command log) is
//! `station_web`'s.

pub mod background;
pub mod plan;
pub mod state;
pub mod web;

use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use anyhow::Context;
use flightplan::api::items as fpma;
use flightplan::api::CommandAck;
use flightplan::vehicle::VehicleParams;
use marea::{FunctionItem, Service};
use station_web::{call_error, Live, StationConfig};
use tokio_util::sync::CancellationToken;
use usal_types::items::vas;
use usal_types::{CommandReply, FlightState, StateChangeReply, StateChangeRequest, VehicleCommand};

use crate::background::{Background, BackgroundSource};
use crate::plan::CheckedPlan;
pub use crate::state::{fpma_prefix, State};
use crate::state::{label_of, Stamped};

/// Everything the FPMo needs.
#[derive(Clone, Debug)]
pub struct FpmoConfig {
    /// What every station needs: network, node, HTTP address, staleness, call time limit.
    pub station: StationConfig,
    /// Namespace pattern of the vehicles followed: `*` (a fleet, each `<ns>/fpma` and
    /// `<ns>/vas`), or one namespace such as `rover1`.
    pub vehicles: String,
    /// Vehicle parameters uploads are checked with (as the FPMa's `vehicle`).
    pub vehicle: VehicleParams,
    /// A georeferenced image drawn under the map.
    pub background: Option<Background>,
}

impl Default for FpmoConfig {
    fn default() -> Self {
        Self {
            station: StationConfig::new("fpmo", 8082),
            vehicles: "*".into(),
            vehicle: VehicleParams::rover(),
            background: None,
        }
    }
}

/// How long an uploaded plan may take to be loaded or refused after delivery.
const LOAD_TIMEOUT: Duration = Duration::from_secs(30);
/// How often the drawings are compared with the progress' plan version.
const GEOMETRY_CHECK: Duration = Duration::from_secs(1);

/// What the handlers and the middleware tasks share.
pub struct Shared {
    state: Mutex<State>,
    svc: Service,
    /// Change notification, cancellation and tasks.
    pub live: Live,
    vehicle: VehicleParams,
    call_timeout: Duration,
    uploads: tempfile::TempDir,
    probes: Mutex<HashMap<String, ()>>,
    /// The map's background image, if any.
    pub background: Option<Background>,
    /// The map's tiles, if any.
    pub tiles: Option<Arc<station_web::tiles::Tiles>>,
    /// A flight log being played back (`usal replay`), shown as a REPLAY.
    pub replay: station_web::replay::ReplayWatch,
}

impl Shared {
    /// The state; a poisoned lock is taken over (nothing in it can be left half-updated in a
    /// way worth stopping the station for).
    pub fn state(&self) -> MutexGuard<'_, State> {
        marea::sync::lock(&self.state)
    }

    /// The commanded vehicle, or the one named.
    pub fn target(&self, vehicle: Option<String>) -> Result<String, String> {
        match vehicle {
            Some(v) => Ok(v),
            None => self
                .state()
                .selected
                .clone()
                .ok_or_else(|| "no vehicle heard yet".to_string()),
        }
    }

    /// Chooses the vehicle commanded.
    pub fn select(&self, label: &str) -> Result<(), String> {
        let mut st = self.state();
        if !st.vehicles.contains_key(label) {
            return Err(format!("unknown vehicle `{label}`"));
        }
        st.selected = Some(label.to_owned());
        Ok(())
    }

    /// Calls `label`'s FPMa function `item` in the background as command `what`; `then` runs
    /// on success with the answer (under the state lock) and returns the confirmation text.
    pub fn command<A: marea::Payload, R: marea::Payload>(
        self: &Arc<Self>,
        label: &str,
        item: FunctionItem<A, R>,
        what: String,
        args: A,
        then: impl FnOnce(&mut State, &R) -> String + Send + 'static,
    ) -> u64 {
        self.call_as_command(label, item, fpma_prefix(label), what, args, then)
    }

    /// Asks `label`'s VAS for flight state `to` (its `change_state`), as a command of the
    /// log; refused here unless the VAS offers it from the state it is in.
    ///
    /// # Errors
    /// `to` is not among the changes offered (the reason names what is).
    pub fn change_state(self: &Arc<Self>, label: &str, to: FlightState) -> Result<u64, String> {
        let what = {
            let st = self.state();
            let v = st
                .vehicles
                .get(label)
                .ok_or_else(|| format!("unknown vehicle `{label}`"))?;
            let offers = v.offers();
            let Some(o) = offers.iter().find(|o| o.to == to) else {
                let from = v
                    .flight_state
                    .as_ref()
                    .map_or_else(|| "an unknown state".to_owned(), |s| s.value.to_string());
                let names: Vec<&str> = offers.iter().map(|o| o.to.name()).collect();
                return Err(format!(
                    "{to} is not offered from {from} (offered: {})",
                    if names.is_empty() {
                        "none yet".to_owned()
                    } else {
                        names.join(", ")
                    }
                ));
            };
            if o.label == "Start" {
                format!("Start (change_state {to})")
            } else {
                format!("change_state {to}")
            }
        };
        Ok(self.call_as_command(
            label,
            vas::CHANGE_STATE,
            vas_prefix(label),
            what,
            StateChangeRequest { to },
            |_, r: &StateChangeReply| format!("{} -> {}", r.from, r.to),
        ))
    }

    /// Sends `label`'s VAS the command `name` (`ARM`, `DISARM`) as a command of the log;
    /// refused here unless the VAS offers it from the state it is in.
    ///
    /// # Errors
    /// Not offered (the reason names what is).
    pub fn vehicle_command(self: &Arc<Self>, label: &str, name: &str) -> Result<u64, String> {
        let cmd = match name {
            "ARM" => VehicleCommand::Arm,
            "DISARM" => VehicleCommand::Disarm,
            other => return Err(format!("unknown vehicle command `{other}` (ARM, DISARM)")),
        };
        {
            let st = self.state();
            let v = st
                .vehicles
                .get(label)
                .ok_or_else(|| format!("unknown vehicle `{label}`"))?;
            let offered = v.command_offers();
            if !offered.iter().any(|c| c == name) {
                let from = v
                    .flight_state
                    .as_ref()
                    .map_or_else(|| "an unknown state".to_owned(), |s| s.value.to_string());
                return Err(format!(
                    "{name} is not offered in {from} (offered: {})",
                    if offered.is_empty() {
                        "none".to_owned()
                    } else {
                        offered.join(", ")
                    }
                ));
            }
        }
        Ok(self.call_as_command(
            label,
            vas::COMMAND,
            vas_prefix(label),
            name.to_owned(),
            cmd,
            |_, r: &CommandReply| format!("{} in {}", r.command, r.state),
        ))
    }

    /// Calls function `item` of the service at `prefix` in the background as command `what`
    /// of `label`.
    fn call_as_command<A: marea::Payload, R: marea::Payload>(
        self: &Arc<Self>,
        label: &str,
        item: FunctionItem<A, R>,
        prefix: String,
        what: String,
        args: A,
        then: impl FnOnce(&mut State, &R) -> String + Send + 'static,
    ) -> u64 {
        let id = self.state().start(label, what, None);
        self.live.changed.notify_waiters();
        let me = self.clone();
        self.live.tasks.spawn(async move {
            let outcome = async {
                let f = item.function(&me.svc, &prefix).map_err(|e| e.to_string())?;
                if !f.has_provider() && !f.wait_provider(me.call_timeout).await {
                    return Err(format!("no service provides {}", item.at(&prefix)));
                }
                tokio::select! {
                    r = f.call(&args, me.call_timeout) => r.map_err(call_error),
                    _ = me.live.cancel.cancelled() => Err("station stopping".into()),
                }
            }
            .await;
            {
                let mut st = me.state();
                let outcome = outcome.map(|r| then(&mut st, &r));
                st.finish(id, outcome);
            }
            me.live.changed.notify_waiters();
        });
        id
    }

    /// Checks `xml` here, then sends it to the FPMa's `plans` sink; pending until the FPMa
    /// loads or refuses it.
    ///
    /// # Errors
    /// The plan does not parse (nothing is sent), or the file cannot be staged.
    pub fn upload(self: &Arc<Self>, label: &str, file: &str, xml: &str) -> Result<u64, String> {
        let file: String = file
            .chars()
            .map(|c| {
                if c.is_ascii_alphanumeric() || matches!(c, '.' | '-' | '_') {
                    c
                } else {
                    '_'
                }
            })
            .collect();
        let file = if file.is_empty() {
            "plan.xml".to_owned()
        } else {
            file
        };
        let local = CheckedPlan::check(&file, xml, &self.vehicle)?;
        let dir = self
            .uploads
            .path()
            .join(format!("{}", self.state().next_id));
        std::fs::create_dir_all(&dir).map_err(|e| e.to_string())?;
        let path = dir.join(&file);
        std::fs::write(&path, xml).map_err(|e| e.to_string())?;
        let what = format!("upload {file} ({} legs)", local.legs);
        let id = self.state().start(label, what, Some(local));
        self.live.changed.notify_waiters();
        let sink = format!("{}/plans", fpma_prefix(label));
        let transfer = self.svc.send_file(
            &path,
            &sink,
            marea::SendFileOptions {
                retry_for: self.call_timeout.max(Duration::from_secs(5)),
                ..Default::default()
            },
        );
        let me = self.clone();
        self.live.tasks.spawn(async move {
            let mut progress = transfer.watch_progress();
            let result = {
                let wait = transfer.wait();
                tokio::pin!(wait);
                loop {
                    tokio::select! {
                        r = &mut wait => break r,
                        c = progress.changed() => {
                            if c.is_ok() {
                                let p = *progress.borrow();
                                // The FPMa loads a plan before its sink says stored, so the
                                // plan's own event may have settled the command already.
                                me.state().commands.progress(
                                    id,
                                    format!("sending {}/{} bytes", p.acknowledged, p.total),
                                );
                                me.live.changed.notify_waiters();
                            }
                        }
                        _ = me.live.cancel.cancelled() => return,
                    }
                }
            };
            match result {
                Ok(r) => {
                    me.state().commands.progress(
                        id,
                        format!(
                            "delivered {} bytes to {}, waiting for the FPMa to load it",
                            r.size, r.receiver
                        ),
                    );
                    me.live.changed.notify_waiters();
                    tokio::select! {
                        _ = tokio::time::sleep(LOAD_TIMEOUT) => {}
                        _ = me.live.cancel.cancelled() => return,
                    }
                    me.state().finish(
                        id,
                        Err("the FPMa neither loaded nor refused the plan".into()),
                    );
                }
                Err(e) => me.state().finish(id, Err(e.to_string())),
            }
            me.live.changed.notify_waiters();
        });
        Ok(id)
    }

    /// Asks the FPMa of `label` for its plan geometry and draws the answer.
    async fn fetch_geometry(&self, label: &str) {
        let fpma_at = fpma_prefix(label);
        let answer = match fpma::PLAN_GEOMETRY.function(&self.svc, &fpma_at) {
            Ok(f) => tokio::select! {
                r = f.call(&(), self.call_timeout) => r.map_err(call_error),
                _ = self.live.cancel.cancelled() => return,
            },
            Err(e) => Err(e.to_string()),
        };
        match answer {
            Ok(g) => {
                self.state().geometry(label, g);
                self.live.changed.notify_waiters();
            }
            Err(e) => tracing::debug!("{}: {e}", fpma::PLAN_GEOMETRY.at(&fpma_at)),
        }
    }

    /// A probe of the FPMa of `label`, whose provider's presence tells whether it is reachable
    /// (progress is published on change only, so its age says nothing).
    fn ensure_probe(&self, label: &str) {
        let mut probes = marea::sync::lock(&self.probes);
        if probes.contains_key(label) {
            return;
        }
        if let Ok(f) = fpma::SKIP_LEG.function(&self.svc, &fpma_prefix(label)) {
            self.state().vehicle(label).probe = Some(Arc::new(f));
            probes.insert(label.to_owned(), ());
        }
    }
}

/// Modifies leg `leg` with `changes` (attributes as in the XML, metres); the map is redrawn
/// when the FPMa publishes the new version's geometry.
pub fn modify_leg(
    shared: &Arc<Shared>,
    label: &str,
    leg: String,
    changes: Vec<(String, String)>,
) -> u64 {
    let what = format!(
        "modify {leg}: {}",
        changes
            .iter()
            .map(|(a, v)| format!("{a}={v}"))
            .collect::<Vec<_>>()
            .join(", ")
    );
    let args = flightplan::api::ModifyLeg { leg, changes };
    shared.command(
        label,
        fpma::MODIFY_LEG,
        what,
        args,
        |_, ack: &CommandAck| format!("version {}", ack.version),
    )
}

fn spawn_sub<T: marea::Payload>(
    shared: &Arc<Shared>,
    sub: marea::Subscription<T>,
    service: &'static str,
    apply: fn(&mut State, &str, T),
) {
    let me = shared.clone();
    shared.live.follow(sub, service, move |s| {
        let Some(label) = label_of(&s.name, service) else {
            return;
        };
        if service == "fpma" {
            me.ensure_probe(&label);
        }
        apply(&mut me.state(), &label, s.value);
        if service == "fpma" {
            me.live.changed.notify_waiters();
        }
    });
}

/// The `vas` prefix of a vehicle label (`rover1` → `rover1/vas`, `` → `vas`).
pub fn vas_prefix(label: &str) -> String {
    if label.is_empty() {
        "vas".into()
    } else {
        format!("{label}/vas")
    }
}

/// Follows one of the VAS's state items; every change is shown at once (unlike positions).
fn spawn_vas_state_sub<T: marea::Payload>(
    shared: &Arc<Shared>,
    sub: marea::Subscription<T>,
    apply: fn(&mut crate::state::Vehicle, T),
) {
    let me = shared.clone();
    shared.live.follow(sub, "vas", move |s| {
        let Some(label) = label_of(&s.name, "vas") else {
            return;
        };
        apply(me.state().vehicle(&label), s.value);
        me.live.changed.notify_waiters();
    });
}

/// Asks an FPMa for its plan when the drawing lags its progress (see [`GEOMETRY_LAG`]).
async fn geometry_loop(me: Arc<Shared>) {
    let mut tick = tokio::time::interval(GEOMETRY_CHECK);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = me.live.cancel.cancelled() => return,
        }
        let lagging = me.state().geometry_lagging(Instant::now(), |v| {
            v.probe.as_ref().is_some_and(|f| f.has_provider())
        });
        for label in lagging {
            me.fetch_geometry(&label).await;
        }
    }
}

/// Runs the FPMo until `shutdown`: binds, prints `FPMO_URL=http://ADDR/?token=TOKEN`, opens the node,
/// serves.
///
/// # Errors
/// The address cannot be bound, a bad network file or pattern, a node that cannot open.
pub async fn run(config: FpmoConfig, shutdown: CancellationToken) -> anyhow::Result<()> {
    if let Some(Background {
        source: BackgroundSource::File(path),
        ..
    }) = &config.background
    {
        let meta = std::fs::metadata(path)
            .with_context(|| format!("background image {}", path.display()))?;
        anyhow::ensure!(
            meta.is_file(),
            "background image {} is not a file",
            path.display()
        );
    }
    let tiles = config.station.open_tiles()?;
    let (listener, addr) = station_web::bind(config.station.listen, "FPMO_URL").await?;
    let node = station_web::open_node(&config.station).await?;
    let svc = node.service("fpmo").context("declaring the fpmo service")?;
    let cancel = shutdown.child_token();
    let shared = Arc::new(Shared {
        state: Mutex::new(State::new(config.station.stale_after)),
        svc: svc.clone(),
        vehicle: config.vehicle.clone(),
        call_timeout: config.station.call_timeout,
        uploads: tempfile::tempdir().context("staging directory for uploads")?,
        live: Live::new(cancel.clone()),
        probes: Mutex::new(HashMap::new()),
        background: config.background.clone(),
        tiles,
        replay: station_web::replay::ReplayWatch::default(),
    });
    shared.replay.follow(&svc, &shared.live)?;
    // `*` also matches nothing, so a vehicle without namespace is followed too.
    let ns = if config.vehicles == "*" {
        "**".to_owned()
    } else {
        config.vehicles.clone()
    };
    let (fpmas, vases) = (format!("{ns}/fpma"), format!("{ns}/vas"));
    spawn_sub(
        &shared,
        fpma::PROGRESS.subscribe(&svc, &fpmas)?,
        "fpma",
        |st, l, p| st.vehicle(l).progress = Some(Stamped::now(p)),
    );
    spawn_sub(
        &shared,
        fpma::STATE.subscribe(&svc, &fpmas)?,
        "fpma",
        |st, l, p| st.vehicle(l).plan_state = Some(Stamped::now(p)),
    );
    spawn_sub(
        &shared,
        fpma::PLAN.subscribe(&svc, &fpmas)?,
        "fpma",
        State::geometry,
    );
    spawn_sub(
        &shared,
        fpma::PLAN_EVENT.subscribe(&svc, &fpmas)?,
        "fpma",
        State::plan_event,
    );
    spawn_sub(
        &shared,
        fpma::PLAN_REJECTED.subscribe(&svc, &fpmas)?,
        "fpma",
        State::plan_rejected,
    );
    spawn_sub(
        &shared,
        vas::POSITION.subscribe(&svc, &vases)?,
        "vas",
        State::position,
    );
    spawn_vas_state_sub(
        &shared,
        vas::FLIGHT_STATE.subscribe(&svc, &vases)?,
        |v, s| v.flight_state = Some(Stamped::now(s)),
    );
    spawn_vas_state_sub(&shared, vas::BATTERY.subscribe(&svc, &vases)?, |v, b| {
        v.battery = Some(Stamped::now(b))
    });
    spawn_vas_state_sub(&shared, vas::HOME.subscribe(&svc, &vases)?, |v, h| {
        v.home = Some(h)
    });
    spawn_vas_state_sub(&shared, vas::FENCE.subscribe(&svc, &vases)?, |v, f| {
        v.fence = Some(f)
    });
    spawn_vas_state_sub(
        &shared,
        vas::ALLOWED_CHANGES.subscribe(&svc, &vases)?,
        |v, a| v.allowed = Some(Stamped::now(a)),
    );
    spawn_sub(
        &shared,
        fpma::READY.subscribe(&svc, &fpmas)?,
        "fpma",
        |st, l, r| st.vehicle(l).readiness = Some(Stamped::now(r)),
    );
    shared.live.tasks.spawn(geometry_loop(shared.clone()));
    tracing::info!("fpmo up on http://{addr}/, following {ns}");
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
