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

pub mod background;
pub mod plan;
pub mod web;

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::{Duration, Instant};

use anyhow::Context;
use fmo::model::CommandStatus;
use fpma::api::{
    CommandAck, PlanEvent, PlanEventKind, PlanGeometry, PlanRejected, PlanState, Progress, VarValue,
};
use fpma::vehicle::VehicleParams;
use marea::{Function, RecvError, Service};
use tokio::sync::Notify;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use usal_types::Position;

use crate::background::{Background, BackgroundSource};
use crate::plan::{distance_m, CheckedPlan, PlanView};

/// Everything the FPMo needs.
#[derive(Clone, Debug)]
pub struct FpmoConfig {
    /// The middleware's network.xml; none: Ethernet on loopback.
    pub network: Option<PathBuf>,
    /// Overrides the network file's domain.
    pub domain: Option<String>,
    /// Overrides the network file's namespace.
    pub namespace: Option<String>,
    /// Node name when no network file is given.
    pub node: String,
    /// HTTP address.
    pub listen: SocketAddr,
    /// Namespace pattern of the vehicles followed: `*` (a fleet, each `<ns>/fpma` and
    /// `<ns>/vas`), or one namespace such as `rover1`.
    pub vehicles: String,
    /// Vehicle parameters uploads are checked with (as the FPMa's `vehicle`).
    pub vehicle: VehicleParams,
    /// Values older than this are shown as stale.
    pub stale_after: Duration,
    /// Time limit of each FPMa call.
    pub call_timeout: Duration,
    /// A georeferenced image drawn under the map.
    pub background: Option<Background>,
}

impl Default for FpmoConfig {
    fn default() -> Self {
        Self {
            network: None,
            domain: None,
            namespace: None,
            node: "fpmo".into(),
            listen: SocketAddr::from(([127, 0, 0, 1], 8082)),
            vehicles: "*".into(),
            vehicle: VehicleParams::rover(),
            stale_after: Duration::from_secs(2),
            call_timeout: Duration::from_secs(5),
            background: None,
        }
    }
}

/// Track points kept per vehicle.
const MAX_TRACK: usize = 2000;
/// A new track point when the vehicle moved at least this far.
const TRACK_STEP_M: f64 = 0.5;
/// How long an uploaded plan may take to be loaded or refused after delivery.
const LOAD_TIMEOUT: Duration = Duration::from_secs(30);
/// How often the drawings are compared with the progress' plan version.
const GEOMETRY_CHECK: Duration = Duration::from_secs(1);
/// A drawing older than the progress for this long is asked for (`plan_geometry`): the `plan`
/// variable was lost (a lossy radio) or is still on its way (it usually is, briefly).
const GEOMETRY_LAG: Duration = Duration::from_secs(3);
/// Least time between two `plan_geometry` calls to one FPMa.
const GEOMETRY_RETRY: Duration = Duration::from_secs(5);

#[derive(Clone, Debug)]
struct Stamped<T> {
    value: T,
    at: Instant,
}

#[derive(Default)]
struct Vehicle {
    progress: Option<Stamped<Progress>>,
    /// The executive's variables and loop passes (the FPMa's `state`).
    plan_state: Option<Stamped<PlanState>>,
    position: Option<Stamped<Position>>,
    track: VecDeque<(f64, f64)>,
    /// The FPMa's plan as it last said (version 0: none loaded).
    geometry: Option<PlanGeometry>,
    /// Grows with every new drawing, so the page knows to fetch it.
    plan_rev: u64,
    /// Since when the drawing lags the progress' version.
    geometry_lags_since: Option<Instant>,
    /// When `plan_geometry` was last called.
    geometry_asked: Option<Instant>,
    events: VecDeque<(Instant, String)>,
    probe: Option<Arc<Function<(), CommandAck>>>,
}

struct Cmd {
    id: u64,
    vehicle: String,
    what: String,
    status: CommandStatus,
    detail: String,
    started: Instant,
    finished: Option<Instant>,
    /// An upload waiting for `PlanLoaded { name }` / `plan_rejected { file }`.
    upload: Option<CheckedPlan>,
}

/// The station's state.
pub struct State {
    vehicles: BTreeMap<String, Vehicle>,
    selected: Option<String>,
    commands: VecDeque<Cmd>,
    next_id: u64,
    stale_after: Duration,
}

fn ms(d: Duration) -> u64 {
    u64::try_from(d.as_millis()).unwrap_or(u64::MAX)
}

/// The `fpma` prefix of a vehicle label (`rover1` → `rover1/fpma`, `` → `fpma`).
pub fn fpma_prefix(label: &str) -> String {
    if label.is_empty() {
        "fpma".into()
    } else {
        format!("{label}/fpma")
    }
}

/// The vehicle label of an item name: what precedes `/<service>/<item>`.
fn label_of(name: &str, service: &str) -> Option<String> {
    let cut = name.rfind(&format!("{service}/"))?;
    Some(name[..cut].trim_end_matches('/').to_owned())
}

impl State {
    fn vehicle(&mut self, label: &str) -> &mut Vehicle {
        if self.selected.is_none() {
            self.selected = Some(label.to_owned());
        }
        self.vehicles.entry(label.to_owned()).or_default()
    }

    fn start(&mut self, vehicle: &str, what: String, upload: Option<CheckedPlan>) -> u64 {
        let id = self.next_id;
        self.next_id += 1;
        self.commands.push_back(Cmd {
            id,
            vehicle: vehicle.to_owned(),
            what,
            status: CommandStatus::Pending,
            detail: String::new(),
            started: Instant::now(),
            finished: None,
            upload,
        });
        while self.commands.len() > 30 {
            match self
                .commands
                .iter()
                .position(|c| c.status != CommandStatus::Pending)
            {
                Some(i) => {
                    self.commands.remove(i);
                }
                None => break,
            }
        }
        id
    }

    fn cmd(&mut self, id: u64) -> Option<&mut Cmd> {
        self.commands.iter_mut().find(|c| c.id == id)
    }

    fn finish(&mut self, id: u64, outcome: Result<String, String>) {
        if let Some(c) = self.cmd(id) {
            if c.status != CommandStatus::Pending {
                return;
            }
            (c.status, c.detail) = match outcome {
                Ok(d) => (CommandStatus::Ok, d),
                Err(e) => (CommandStatus::Failed, e),
            };
            c.finished = Some(Instant::now());
        }
    }

    /// The FPMa's plan geometry (variable `plan` or an answer of `plan_geometry`).
    fn geometry(&mut self, label: &str, g: PlanGeometry) {
        let v = self.vehicle(label);
        if v.geometry.as_ref() != Some(&g) {
            v.geometry = Some(g);
            v.plan_rev += 1;
        }
    }

    /// Vehicles whose drawing has lagged their progress long enough to ask for it again,
    /// among those whose FPMa is `reachable`.
    fn geometry_lagging(
        &mut self,
        now: Instant,
        reachable: impl Fn(&Vehicle) -> bool,
    ) -> Vec<String> {
        let mut ask = Vec::new();
        for (label, v) in &mut self.vehicles {
            let wanted = v.progress.as_ref().map_or(0, |p| p.value.version);
            let drawn = v.geometry.as_ref().map_or(0, |g| g.version);
            if wanted == drawn || !reachable(v) {
                v.geometry_lags_since = None;
                continue;
            }
            let since = *v.geometry_lags_since.get_or_insert(now);
            let asked_long_ago = v
                .geometry_asked
                .is_none_or(|t| now.saturating_duration_since(t) >= GEOMETRY_RETRY);
            if now.saturating_duration_since(since) >= GEOMETRY_LAG && asked_long_ago {
                v.geometry_asked = Some(now);
                ask.push(label.clone());
            }
        }
        ask
    }

    fn plan_event(&mut self, label: &str, ev: PlanEvent) {
        let text = match &ev.kind {
            PlanEventKind::PlanLoaded { name } => {
                // The upload that sent this plan is confirmed (the map follows the FPMa's `plan`).
                let hit = self.commands.iter_mut().find(|c| {
                    c.vehicle == label
                        && c.status == CommandStatus::Pending
                        && c.upload.as_ref().is_some_and(|p| p.plan.name == *name)
                });
                if let Some(c) = hit {
                    c.status = CommandStatus::Ok;
                    c.detail = format!("loaded as version {}", ev.version);
                    c.finished = Some(Instant::now());
                    c.upload = None;
                }
                format!("plan `{name}` loaded (version {})", ev.version)
            }
            k => format!("{k:?}"),
        };
        let v = self.vehicle(label);
        v.events
            .push_back((Instant::now(), format!("v{}: {text}", ev.version)));
        while v.events.len() > 30 {
            v.events.pop_front();
        }
    }

    fn plan_rejected(&mut self, label: &str, r: PlanRejected) {
        let hit = self.commands.iter_mut().find(|c| {
            c.vehicle == label
                && c.status == CommandStatus::Pending
                && c.upload.as_ref().is_some_and(|p| p.file == r.file)
        });
        if let Some(c) = hit {
            c.status = CommandStatus::Failed;
            c.detail = r.reason.clone();
            c.finished = Some(Instant::now());
            c.upload = None;
        }
        let v = self.vehicle(label);
        v.events
            .push_back((Instant::now(), format!("rejected {}: {}", r.file, r.reason)));
    }

    fn position(&mut self, label: &str, p: Position) {
        let v = self.vehicle(label);
        let pt = (p.lat, p.lon);
        if v.track
            .back()
            .is_none_or(|&last| distance_m(last, pt) >= TRACK_STEP_M)
        {
            v.track.push_back(pt);
            while v.track.len() > MAX_TRACK {
                v.track.pop_front();
            }
        }
        v.position = Some(Stamped {
            value: p,
            at: Instant::now(),
        });
    }

    /// The page's view.
    pub fn snapshot(&self) -> serde_json::Value {
        let now = Instant::now();
        let vehicles: Vec<_> = self
            .vehicles
            .iter()
            .map(|(label, v)| {
                let reachable = v.probe.as_ref().map(|f| f.has_provider());
                let fpma_ok = reachable.unwrap_or(false);
                let pos_age = v
                    .position
                    .as_ref()
                    .map(|p| now.saturating_duration_since(p.at));
                serde_json::json!({
                    "label": label,
                    "fpma": fpma_prefix(label),
                    "fpma_reachable": fpma_ok,
                    "progress": v.progress.as_ref().map(|p| serde_json::json!({
                        "value": p.value,
                        "age_ms": ms(now.saturating_duration_since(p.at)),
                        "stale": !fpma_ok,
                    })),
                    "position": v.position.as_ref().map(|p| serde_json::json!({
                        "value": p.value,
                        "age_ms": pos_age.map(ms),
                        "stale": pos_age.is_none_or(|a| a > self.stale_after),
                    })),
                    "track": v.track,
                    "vars": v.plan_state.as_ref().map(|s| s.value.vars.iter().map(|(name, val)| {
                        let value = match val {
                            VarValue::Bool(b) => serde_json::json!(b),
                            VarValue::Number(n) => serde_json::json!(n),
                        };
                        serde_json::json!({"name": name, "value": value})
                    }).collect::<Vec<_>>()).unwrap_or_default(),
                    "loops": v.plan_state.as_ref().map(|s| s.value.loops.clone()).unwrap_or_default(),
                    "plan_rev": v.plan_rev,
                    "plan_name": v.geometry.as_ref().filter(|g| g.version > 0).map(|g| g.name.clone()),
                    "plan_version": v.geometry.as_ref().map(|g| g.version),
                    "events": v.events.iter().rev().take(12).map(|(t, e)| serde_json::json!({
                        "age_ms": ms(now.saturating_duration_since(*t)), "text": e,
                    })).collect::<Vec<_>>(),
                })
            })
            .collect();
        let commands: Vec<_> = self
            .commands
            .iter()
            .rev()
            .map(|c| {
                serde_json::json!({
                    "id": c.id, "vehicle": c.vehicle, "what": c.what, "status": c.status,
                    "detail": c.detail,
                    "age_ms": ms(now.saturating_duration_since(c.started)),
                    "took_ms": c.finished.map(|f| ms(f.saturating_duration_since(c.started))),
                })
            })
            .collect();
        serde_json::json!({
            "selected": self.selected,
            "stale_after_ms": ms(self.stale_after),
            "vehicles": vehicles,
            "commands": commands,
        })
    }

    /// The plan of `label` for the map and the legs table, as its FPMa flies it.
    pub fn plan_view(&self, label: &str) -> Option<PlanView> {
        let v = self.vehicles.get(label)?;
        let g = v.geometry.as_ref().filter(|g| g.version > 0)?;
        Some(PlanView::of(g, v.plan_rev))
    }
}

/// What the handlers and the middleware tasks share.
pub struct Shared {
    state: Mutex<State>,
    svc: Service,
    /// Woken when the page should get a snapshot at once.
    pub changed: Notify,
    vehicle: VehicleParams,
    call_timeout: Duration,
    uploads: tempfile::TempDir,
    tasks: TaskTracker,
    cancel: CancellationToken,
    probes: Mutex<HashMap<String, ()>>,
    /// The map's background image, if any.
    pub background: Option<Background>,
}

/// A call error as the operator reads it: the FPMa's own reason when it refused.
fn call_error(e: marea::CallError) -> String {
    match e {
        marea::CallError::Remote { message, .. } => message,
        e => e.to_string(),
    }
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

    /// Calls `<fpma>/name` in the background as command `what`; `then` runs on success with
    /// the answer (under the state lock) and returns the confirmation text.
    pub fn command<A: marea::Payload, R: marea::Payload>(
        self: &Arc<Self>,
        label: &str,
        name: &str,
        what: String,
        args: A,
        then: impl FnOnce(&mut State, &R) -> String + Send + 'static,
    ) -> u64 {
        let id = self.state().start(label, what, None);
        self.changed.notify_waiters();
        let me = self.clone();
        let full = format!("{}/{name}", fpma_prefix(label));
        self.tasks.spawn(async move {
            let outcome = async {
                let f = me.svc.function::<A, R>(&full).map_err(|e| e.to_string())?;
                if !f.has_provider() && !f.wait_provider(me.call_timeout).await {
                    return Err(format!("no FPMa provides {full}"));
                }
                tokio::select! {
                    r = f.call(&args, me.call_timeout) => r.map_err(call_error),
                    _ = me.cancel.cancelled() => Err("station stopping".into()),
                }
            }
            .await;
            {
                let mut st = me.state();
                let outcome = outcome.map(|r| then(&mut st, &r));
                st.finish(id, outcome);
            }
            me.changed.notify_waiters();
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
        self.changed.notify_waiters();
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
        self.tasks.spawn(async move {
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
                                if let Some(c) = me.state().cmd(id) {
                                    c.detail = format!("sending {}/{} bytes", p.acknowledged, p.total);
                                }
                                me.changed.notify_waiters();
                            }
                        }
                        _ = me.cancel.cancelled() => return,
                    }
                }
            };
            match result {
                Ok(r) => {
                    if let Some(c) = me.state().cmd(id) {
                        if c.status == CommandStatus::Pending {
                            c.detail = format!(
                                "delivered {} bytes to {}, waiting for the FPMa to load it",
                                r.size, r.receiver
                            );
                        }
                    }
                    me.changed.notify_waiters();
                    tokio::select! {
                        _ = tokio::time::sleep(LOAD_TIMEOUT) => {}
                        _ = me.cancel.cancelled() => return,
                    }
                    me.state()
                        .finish(id, Err("the FPMa neither loaded nor refused the plan".into()));
                }
                Err(e) => me.state().finish(id, Err(e.to_string())),
            }
            me.changed.notify_waiters();
        });
        Ok(id)
    }

    /// Asks the FPMa of `label` for its plan geometry and draws the answer.
    async fn fetch_geometry(&self, label: &str) {
        let full = format!("{}/plan_geometry", fpma_prefix(label));
        let answer = match self.svc.function::<(), PlanGeometry>(&full) {
            Ok(f) => tokio::select! {
                r = f.call(&(), self.call_timeout) => r.map_err(call_error),
                _ = self.cancel.cancelled() => return,
            },
            Err(e) => Err(e.to_string()),
        };
        match answer {
            Ok(g) => {
                self.state().geometry(label, g);
                self.changed.notify_waiters();
            }
            Err(e) => tracing::debug!("{full}: {e}"),
        }
    }

    /// A probe of the FPMa of `label`, whose provider's presence tells whether it is reachable
    /// (progress is published on change only, so its age says nothing).
    fn ensure_probe(&self, label: &str) {
        let mut probes = marea::sync::lock(&self.probes);
        if probes.contains_key(label) {
            return;
        }
        if let Ok(f) = self
            .svc
            .function::<(), CommandAck>(&format!("{}/skip_leg", fpma_prefix(label)))
        {
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
    let args = fpma::api::ModifyLeg { leg, changes };
    shared.command(label, "modify_leg", what, args, |_, ack: &CommandAck| {
        format!("version {}", ack.version)
    })
}

fn spawn_sub<T: marea::Payload>(
    shared: &Arc<Shared>,
    sub: marea::Subscription<T>,
    service: &'static str,
    apply: fn(&mut State, &str, T),
) {
    let me = shared.clone();
    shared.tasks.spawn(async move {
        loop {
            let got = tokio::select! {
                r = sub.recv() => r,
                _ = me.cancel.cancelled() => return,
            };
            match got {
                Ok(s) => {
                    let Some(label) = label_of(&s.name, service) else {
                        continue;
                    };
                    if service == "fpma" {
                        me.ensure_probe(&label);
                    }
                    apply(&mut me.state(), &label, s.value);
                    if service == "fpma" {
                        me.changed.notify_waiters();
                    }
                }
                Err(RecvError::Closed) => return,
                Err(e) => tracing::warn!("{service}: {e}"),
            }
        }
    });
}

/// Asks an FPMa for its plan when the drawing lags its progress (see [`GEOMETRY_LAG`]).
async fn geometry_loop(me: Arc<Shared>) {
    let mut tick = tokio::time::interval(GEOMETRY_CHECK);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = me.cancel.cancelled() => return,
        }
        let lagging = me.state().geometry_lagging(Instant::now(), |v| {
            v.probe.as_ref().is_some_and(|f| f.has_provider())
        });
        for label in lagging {
            me.fetch_geometry(&label).await;
        }
    }
}

/// Runs the FPMo until `shutdown`: binds, prints `FPMO_URL=http://ADDR/`, opens the node,
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
    let listener = tokio::net::TcpListener::bind(config.listen)
        .await
        .with_context(|| format!("listening on {}", config.listen))?;
    let addr = listener.local_addr().context("local address")?;
    fmo::web::print_url("FPMO_URL", addr);
    let node = fmo::open_node(
        config.network.as_deref(),
        config.domain.as_deref(),
        config.namespace.as_deref(),
        &config.node,
    )
    .await?;
    let svc = node.service("fpmo").context("declaring the fpmo service")?;
    let cancel = shutdown.child_token();
    let shared = Arc::new(Shared {
        state: Mutex::new(State {
            vehicles: BTreeMap::new(),
            selected: None,
            commands: VecDeque::new(),
            next_id: 1,
            stale_after: config.stale_after,
        }),
        svc: svc.clone(),
        changed: Notify::new(),
        vehicle: config.vehicle.clone(),
        call_timeout: config.call_timeout,
        uploads: tempfile::tempdir().context("staging directory for uploads")?,
        tasks: TaskTracker::new(),
        cancel: cancel.clone(),
        probes: Mutex::new(HashMap::new()),
        background: config.background.clone(),
    });
    // `*` also matches nothing, so a vehicle without namespace is followed too.
    let ns = if config.vehicles == "*" {
        "**".to_owned()
    } else {
        config.vehicles.clone()
    };
    spawn_sub(
        &shared,
        svc.subscribe_variable::<Progress>(&format!("{ns}/fpma/progress"))?,
        "fpma",
        |st, l, p| {
            st.vehicle(l).progress = Some(Stamped {
                value: p,
                at: Instant::now(),
            })
        },
    );
    spawn_sub(
        &shared,
        svc.subscribe_variable::<PlanState>(&format!("{ns}/fpma/state"))?,
        "fpma",
        |st, l, p| {
            st.vehicle(l).plan_state = Some(Stamped {
                value: p,
                at: Instant::now(),
            })
        },
    );
    spawn_sub(
        &shared,
        svc.subscribe_variable::<PlanGeometry>(&format!("{ns}/fpma/plan"))?,
        "fpma",
        State::geometry,
    );
    spawn_sub(
        &shared,
        svc.subscribe_event::<PlanEvent>(&format!("{ns}/fpma/plan_event"))?,
        "fpma",
        State::plan_event,
    );
    spawn_sub(
        &shared,
        svc.subscribe_event::<PlanRejected>(&format!("{ns}/fpma/plan_rejected"))?,
        "fpma",
        State::plan_rejected,
    );
    spawn_sub(
        &shared,
        svc.subscribe_variable::<Position>(&format!("{ns}/vas/position"))?,
        "vas",
        State::position,
    );
    shared.tasks.spawn(geometry_loop(shared.clone()));
    tracing::info!("fpmo up on http://{addr}/, following {ns}");
    let served = fmo::web::serve(listener, web::router(shared.clone()), cancel.clone()).await;
    cancel.cancel();
    shared.tasks.close();
    shared.tasks.wait().await;
    drop(shared);
    drop(svc);
    node.shutdown().await;
    served
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn labels_of_item_names() {
        assert_eq!(
            label_of("rover1/fpma/progress", "fpma").as_deref(),
            Some("rover1")
        );
        assert_eq!(label_of("a/b/vas/position", "vas").as_deref(), Some("a/b"));
        assert_eq!(label_of("fpma/progress", "fpma").as_deref(), Some(""));
        assert_eq!(fpma_prefix(""), "fpma");
        assert_eq!(fpma_prefix("rover1"), "rover1/fpma");
    }

    #[test]
    fn a_drawing_lagging_the_progress_is_asked_for_after_a_while_and_not_too_often() {
        let mut st = State {
            vehicles: BTreeMap::new(),
            selected: None,
            commands: VecDeque::new(),
            next_id: 1,
            stale_after: Duration::from_secs(2),
        };
        let t = Instant::now();
        let progress = |version| Progress {
            version,
            ..Progress::default()
        };
        let geometry = |version| PlanGeometry {
            version,
            ..PlanGeometry::default()
        };
        st.vehicle("r").progress = Some(Stamped {
            value: progress(2),
            at: t,
        });
        st.geometry("r", geometry(2));
        assert_eq!(st.vehicles["r"].plan_rev, 1);
        st.geometry("r", geometry(2));
        assert_eq!(
            st.vehicles["r"].plan_rev, 1,
            "the same drawing is not redrawn"
        );
        assert!(st.geometry_lagging(t, |_| true).is_empty(), "up to date");

        // Progress says version 3; the drawing is still 2 (the `plan` value lost or late).
        st.vehicle("r").progress = Some(Stamped {
            value: progress(3),
            at: t,
        });
        assert!(st.geometry_lagging(t, |_| true).is_empty(), "give it time");
        assert!(
            st.geometry_lagging(t + GEOMETRY_LAG, |_| false).is_empty(),
            "an unreachable FPMa is not asked"
        );
        assert!(
            st.geometry_lagging(t + GEOMETRY_LAG, |_| true).is_empty(),
            "lag restarts"
        );
        let later = t + GEOMETRY_LAG * 2;
        assert_eq!(st.geometry_lagging(later, |_| true), ["r"]);
        assert!(st
            .geometry_lagging(later + Duration::from_secs(1), |_| true)
            .is_empty());
        assert_eq!(st.geometry_lagging(later + GEOMETRY_RETRY, |_| true), ["r"]);
        st.geometry("r", geometry(3));
        assert!(st
            .geometry_lagging(later + GEOMETRY_RETRY * 2, |_| true)
            .is_empty());
        assert_eq!(st.plan_view("r").map(|p| p.rev), Some(2));
    }
}
