//! The networked `fpma` service (`fpma run`): hosts one [`Executive`](flightplan::exec::Executive) on a
//! middleware node, takes plans as files or through a function, feeds the VAS's waypoint queue,
//! follows its waypoint-reached events, and offers the in-flight commands as functions. Items
//! and config keys are listed in `services/fpma/README.md`.
//!
//! One task owns the [`core::Core`]; function handlers, the file sink and the VAS subscriptions
//! hand it requests over a channel, so inputs are applied one at a time, in arrival order.

pub mod core;
pub mod persist;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use async_trait::async_trait;
use marea::{Event, Function, FunctionItem, IService, Service, ServiceError, Variable};
use serde::Deserialize;
use tokio::sync::{mpsc, oneshot};
use tokio_util::sync::CancellationToken;
use usal_types::items::vas;
use usal_types::{CommandRecord, QueueStatus, Waypoint};

use self::core::{Command, Core, CoreConfig, FenceRefusal, VasPort};
use flightplan::api::items as fpma;
use flightplan::api::{
    CommandAck, HoldHereArgs, ModifyLeg, PlanEvent, PlanGeometry, PlanLoaded, PlanRejected,
    PlanState, Progress, Readiness, Retask, SetVar,
};
use flightplan::geo::GeoPoint;
use flightplan::model::Stage;
use flightplan::vehicle::{VehicleKind, VehicleParams};

/// Everything `fpma run` needs. Attribute names of the `<fpma .../>` file in brackets.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FpmaConfig {
    /// The middleware's network.xml (`network`); none: Ethernet on loopback.
    #[serde(rename = "@network")]
    pub network: Option<PathBuf>,
    /// Overrides the network file's domain (`domain`).
    #[serde(rename = "@domain")]
    pub domain: Option<String>,
    /// Overrides the network file's namespace (`namespace`), e.g. `rover1`.
    #[serde(rename = "@namespace")]
    pub namespace: Option<String>,
    /// The VAS to feed (`vas`): a service name in this namespace (`vas`) or a full prefix
    /// (`rover1/vas`).
    #[serde(rename = "@vas")]
    pub vas: String,
    /// Vehicle parameters plans are shaped by (`vehicle`): rover, aircraft, copter.
    #[serde(rename = "@vehicle")]
    pub vehicle: VehicleKind,
    /// Overrides the vehicle's minimum distance between waypoints, metres
    /// (`minWaypointDistance`; 003 §6.2.3: 4-5 m for a rover, 100 m for an aircraft).
    #[serde(rename = "@minWaypointDistance")]
    pub min_wp_distance: Option<f64>,
    /// Overrides the vehicle's default speed, m/s (`defaultSpeed`).
    #[serde(rename = "@defaultSpeed")]
    pub default_speed: Option<f64>,
    /// Overrides the vehicle's minimum turn radius, metres (`turnRadius`).
    #[serde(rename = "@turnRadius")]
    pub turn_radius: Option<f64>,
    /// Waypoints kept in the VAS queue ahead of the vehicle (`lookahead`), ≥ 1. More than the
    /// VAS's rolling-queue slots keeps its window full.
    #[serde(rename = "@lookahead")]
    pub lookahead: usize,
    /// Ignored (`startNavigation`), kept so older files load: the FPMa no longer changes the
    /// flight state (pilot in command). A loaded plan waits for the operator's
    /// WAYPOINT_NAVIGATION and says so in the variable `ready`.
    #[serde(rename = "@startNavigation")]
    pub start_navigation: bool,
    /// Where plan files sent to `fpma/plans` are stored (`plansDir`); none: under the user's
    /// state directory (`$XDG_STATE_HOME/usal/sinks/<namespace>_fpma_plans`).
    #[serde(rename = "@plansDir")]
    pub plans_dir: Option<PathBuf>,
    /// Where the plan and progress are persisted (`stateDir`); none: the user's state
    /// directory, `$XDG_STATE_HOME/usal/<namespace>/fpma` (else `~/.local/state/usal/...`).
    #[serde(rename = "@stateDir")]
    pub state_dir: Option<PathBuf>,
    /// A plan to load at start (`plan`).
    #[serde(rename = "@plan")]
    pub plan: Option<PathBuf>,
    /// Time limit of each call to the VAS, ms (`callTimeoutMs`).
    #[serde(rename = "@callTimeoutMs")]
    pub call_timeout_ms: u64,
}

impl Default for FpmaConfig {
    fn default() -> Self {
        Self {
            network: None,
            domain: None,
            namespace: None,
            vas: "vas".into(),
            vehicle: VehicleKind::Rover,
            min_wp_distance: None,
            default_speed: None,
            turn_radius: None,
            lookahead: 8,
            start_navigation: false,
            plans_dir: None,
            state_dir: None,
            plan: None,
            call_timeout_ms: 5000,
        }
    }
}

/// Most waypoints the FPMa keeps queued at the VAS: a look-ahead is recomputed after every
/// input, and the point of it is to be short (late changes take effect).
pub const MAX_LOOKAHEAD: usize = 1000;

/// Errors loading the configuration file.
#[derive(Debug, thiserror::Error)]
pub enum ConfigLoadError {
    /// The file cannot be read.
    #[error("cannot read {path}: {source}")]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// Malformed XML, unknown or ill-typed attributes.
    #[error("{}:{source}", path.display())]
    Parse {
        /// The file.
        path: PathBuf,
        /// What was refused, and where.
        source: Box<marea::xml::de::XmlDeError>,
    },
    /// A value out of range.
    #[error("{0}")]
    Invalid(String),
}

impl FpmaConfig {
    /// Reads a `<fpma .../>` file.
    ///
    /// # Errors
    /// Unreadable file, malformed XML, unknown attribute, bad value.
    pub fn load(path: &Path) -> Result<Self, ConfigLoadError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigLoadError::Read {
            path: path.to_owned(),
            source,
        })?;
        let cfg: Self =
            marea::xml::de::from_document(&text).map_err(|e| ConfigLoadError::Parse {
                path: path.to_owned(),
                source: Box::new(e),
            })?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Checks the ranges.
    ///
    /// # Errors
    /// The first value out of range.
    pub fn validate(&self) -> Result<(), ConfigLoadError> {
        if !(1..=MAX_LOOKAHEAD).contains(&self.lookahead) {
            return Err(ConfigLoadError::Invalid(format!(
                "lookahead must be between 1 and {MAX_LOOKAHEAD}, not {}",
                self.lookahead
            )));
        }
        if self.call_timeout_ms < 100 {
            return Err(ConfigLoadError::Invalid("callTimeoutMs below 100".into()));
        }
        if self.vas.is_empty() {
            return Err(ConfigLoadError::Invalid("vas is empty".into()));
        }
        self.vehicle_params()?;
        Ok(())
    }

    /// The parameters of `vehicle` with the overrides applied.
    ///
    /// # Errors
    /// An override that is not a positive number (a turn radius may be 0).
    pub fn vehicle_params(&self) -> Result<VehicleParams, ConfigLoadError> {
        let mut v = VehicleParams::for_kind(self.vehicle);
        for (name, value, slot, zero_ok) in [
            (
                "minWaypointDistance",
                self.min_wp_distance,
                &mut v.min_wp_distance,
                false,
            ),
            (
                "defaultSpeed",
                self.default_speed,
                &mut v.default_speed,
                false,
            ),
            ("turnRadius", self.turn_radius, &mut v.turn_radius, true),
        ] {
            if let Some(x) = value {
                if !x.is_finite() || x < 0.0 || (x == 0.0 && !zero_ok) {
                    return Err(ConfigLoadError::Invalid(format!(
                        "{name} must be a positive number of {}, not {x}",
                        if name == "defaultSpeed" {
                            "m/s"
                        } else {
                            "metres"
                        }
                    )));
                }
                *slot = x;
            }
        }
        Ok(v)
    }

    /// The directory the plan and progress are persisted in: `stateDir`, else
    /// `<user state dir>/<namespace or "default">/fpma`; `None` when there is no state
    /// directory at all (no `XDG_STATE_HOME`, no `HOME`).
    pub fn state_dir_for(&self, namespace: Option<&str>) -> Option<PathBuf> {
        self.state_dir.clone().or_else(|| {
            marea::state_dir().map(|d| d.join(namespace.unwrap_or("default")).join("fpma"))
        })
    }

    /// The full prefix of the VAS's items, e.g. `rover1/vas`.
    pub fn vas_prefix(&self, namespace: Option<&str>) -> String {
        match namespace {
            Some(ns) if !self.vas.contains('/') => format!("{ns}/{}", self.vas),
            _ => self.vas.clone(),
        }
    }
}

/// Runs the service until `shutdown` is cancelled: opens the node, hosts `fpma`, then shuts
/// everything down.
///
/// # Errors
/// Bad configuration, unreadable network file or initial plan, a node that cannot open.
pub async fn run(config: FpmaConfig, shutdown: CancellationToken) -> anyhow::Result<()> {
    config.validate()?;
    let net = marea::NetworkConfig::for_service(
        config.network.as_deref(),
        "fpma",
        config.domain.as_deref(),
        config.namespace.as_deref(),
    )
    .context("loading the network configuration")?;
    let initial = match &config.plan {
        Some(p) => Some((
            std::fs::read_to_string(p).with_context(|| format!("reading {}", p.display()))?,
            p.display().to_string(),
        )),
        None => None,
    };
    let node = marea::Node::open(&net)
        .await
        .context("opening the middleware node")?;
    let vas = config.vas_prefix(net.namespace.as_deref());
    let state = config.state_dir_for(net.namespace.as_deref());
    match &state {
        Some(d) => tracing::info!("plan and progress persisted in {}", d.display()),
        None => tracing::warn!(
            "no state directory (set stateDir, XDG_STATE_HOME or HOME): a restart starts clean"
        ),
    }
    node.add_service(Box::new(Fpma {
        config: config.clone(),
        vas: vas.clone(),
        initial,
        state: state.map(|d| persist::StateFile::new(&d)),
    }))
    .await
    .context("starting the fpma service")?;
    tracing::info!("fpma up, feeding {vas}");
    shutdown.cancelled().await;
    node.shutdown().await;
    Ok(())
}

/// The VAS's functions over the middleware.
struct MareaVas {
    push: Function<Vec<Waypoint>, QueueStatus>,
    clear: Function<(), QueueStatus>,
    set_fence: Function<Option<usal_types::Fence>, String>,
    timeout: Duration,
}

/// Calls `f`, first waiting up to `timeout` for a provider when none is known (the VAS may
/// not be discovered yet when the first plan arrives).
async fn call_vas<A: marea::Payload, R: marea::Payload>(
    f: &Function<A, R>,
    args: &A,
    timeout: Duration,
) -> Result<R, String> {
    if !f.has_provider() && !f.wait_provider(timeout).await {
        return Err(format!("no VAS provides {}", f.name()));
    }
    f.call(args, timeout).await.map_err(|e| e.to_string())
}

#[async_trait]
impl VasPort for MareaVas {
    async fn push(&self, wps: Vec<Waypoint>) -> Result<QueueStatus, String> {
        call_vas(&self.push, &wps, self.timeout).await
    }

    async fn clear(&self) -> Result<QueueStatus, String> {
        call_vas(&self.clear, &(), self.timeout).await
    }

    async fn set_fence(&self, fence: Option<usal_types::Fence>) -> Result<String, FenceRefusal> {
        let f = &self.set_fence;
        if !f.has_provider() && !f.wait_provider(self.timeout).await {
            return Err(FenceRefusal::Unreachable(format!(
                "no VAS provides {}",
                f.name()
            )));
        }
        f.call(&fence, self.timeout).await.map_err(|e| match e {
            marea::CallError::Remote { message, .. } => FenceRefusal::Refused(message),
            e => FenceRefusal::Unreachable(e.to_string()),
        })
    }
}

/// A request to the core task.
enum Request {
    Load {
        text: String,
        source: String,
        replace: bool,
        reply: oneshot::Sender<Result<PlanLoaded, String>>,
    },
    Command(Command, oneshot::Sender<Result<CommandAck, String>>),
    Geometry(oneshot::Sender<Result<PlanGeometry, String>>),
    Progress(oneshot::Sender<Result<Progress, String>>),
}

/// The `fpma` middleware service.
pub struct Fpma {
    config: FpmaConfig,
    vas: String,
    initial: Option<(String, String)>,
    state: Option<persist::StateFile>,
}

impl Fpma {
    /// A service with `config`, feeding the VAS whose items are under `vas` (a full prefix).
    pub fn new(config: FpmaConfig, vas: String) -> Self {
        Self {
            config,
            vas,
            initial: None,
            state: None,
        }
    }

    /// Persists the plan and progress in `file` and resumes them at start.
    pub fn with_state(mut self, file: persist::StateFile) -> Self {
        self.state = Some(file);
        self
    }
}

/// Published items.
struct Outlets {
    progress: Variable<Progress>,
    state: Variable<PlanState>,
    plan: Variable<PlanGeometry>,
    plan_event: Event<PlanEvent>,
    /// Whether the plan waits for the operator's start.
    ready: Variable<Readiness>,
}

/// Sends `req` to the core and waits for its answer.
async fn ask<T>(
    tx: &mpsc::Sender<Request>,
    make: impl FnOnce(oneshot::Sender<Result<T, String>>) -> Request,
) -> Result<T, String> {
    let (reply, rx) = oneshot::channel();
    tx.send(make(reply))
        .await
        .map_err(|_| "the fpma service is stopping".to_string())?;
    rx.await
        .map_err(|_| "the fpma service is stopping".to_string())?
}

/// The plans sink's check: each plan file received whole is loaded like `load_plan` before it
/// is stored; a refusal is the sender's verdict and is raised as `plan_rejected`.
fn load_on_receipt(
    tx: mpsc::Sender<Request>,
    rejected: Arc<Event<PlanRejected>>,
) -> marea::FileCheck {
    marea::FileCheck::new(move |f: marea::FileToCheck| {
        let (tx, rejected) = (tx.clone(), rejected.clone());
        async move {
            let outcome = match tokio::fs::read_to_string(&f.path).await {
                Ok(text) => ask(&tx, |reply| Request::Load {
                    text,
                    source: f.name.clone(),
                    replace: false,
                    reply,
                })
                .await
                .map(|_| ()),
                Err(e) => Err(format!("{}: cannot read: {e}", f.name)),
            };
            if let Err(reason) = &outcome {
                tracing::warn!("plan file {} from {} refused: {reason}", f.name, f.from);
                let _ = rejected.raise_nowait(&PlanRejected {
                    file: f.name,
                    from: f.from,
                    reason: reason.clone(),
                });
            }
            outcome
        }
    })
}

/// Raises the `commands` event: a command received, who sent it and the answer, for the
/// flight log.
fn record_command<A: std::fmt::Debug, R: std::fmt::Debug>(
    commands: &Event<CommandRecord>,
    from: &marea::Caller,
    name: &str,
    args: &A,
    result: &Result<R, String>,
) {
    let rec = CommandRecord::of(from, name, args, result);
    tracing::info!(from = %rec.from, ok = rec.ok, "{name}({}): {}", rec.args, rec.answer);
    if let Err(e) = commands.raise_nowait(&rec) {
        tracing::warn!("raising commands: {e}");
    }
}

/// Declares `load_plan` (or, with `replace`, `replace_plan`): the XML argument is loaded as
/// the plan; each call is recorded on `commands` with who sent it and the answer.
fn load_fn(
    ctx: &Service,
    tx: &mpsc::Sender<Request>,
    commands: &Arc<Event<CommandRecord>>,
    item: FunctionItem<String, PlanLoaded>,
    replace: bool,
) -> Result<marea::FunctionProvider, ServiceError> {
    let (tx, commands) = (tx.clone(), commands.clone());
    let name = item.name();
    Ok(
        item.provide_with_caller(ctx, move |xml: String, from: marea::Caller| {
            let (tx, commands) = (tx.clone(), commands.clone());
            async move {
                let args = format!("a plan of {} bytes", xml.len());
                let r = ask(&tx, |reply| Request::Load {
                    text: xml,
                    source: "plan".into(),
                    replace,
                    reply,
                })
                .await;
                record_command(&commands, &from, name, &args, &r);
                r
            }
        })?,
    )
}

/// Declares the command function `item` whose argument `A` becomes a [`Command`]; each call
/// is recorded on `commands` with who sent it and the answer.
fn command_fn<A: marea::Payload + std::fmt::Debug>(
    ctx: &Service,
    tx: &mpsc::Sender<Request>,
    commands: &Arc<Event<CommandRecord>>,
    item: FunctionItem<A, CommandAck>,
    to_cmd: fn(A) -> Result<Command, String>,
) -> Result<marea::FunctionProvider, ServiceError> {
    let tx = tx.clone();
    let commands = commands.clone();
    let name = item.name();
    Ok(
        item.provide_with_caller(ctx, move |a: A, from: marea::Caller| {
            let (tx, commands) = (tx.clone(), commands.clone());
            async move {
                let args = format!("{a:?}");
                let r = match to_cmd(a) {
                    Ok(cmd) => ask(&tx, |r| Request::Command(cmd, r)).await,
                    Err(e) => Err(e),
                };
                record_command(&commands, &from, name, &args, &r);
                r
            }
        })?,
    )
}

fn parse_stage(s: &str) -> Result<Stage, String> {
    Stage::ALL
        .into_iter()
        .find(|st| st.to_string() == s.to_ascii_lowercase())
        .ok_or_else(|| {
            format!("unknown stage `{s}` (takeoff, departure, mission, approach, landing)")
        })
}

#[async_trait]
impl IService for Fpma {
    fn name(&self) -> &str {
        "fpma"
    }

    async fn start(&mut self, ctx: Service) -> Result<(), ServiceError> {
        let vehicle = self
            .config
            .vehicle_params()
            .map_err(|e| ServiceError::Failed(e.to_string()))?;
        let outlets = Outlets {
            progress: fpma::PROGRESS.publish(&ctx)?,
            state: fpma::STATE.publish(&ctx)?,
            plan: fpma::PLAN.publish(&ctx)?,
            plan_event: fpma::PLAN_EVENT.publish(&ctx)?,
            ready: fpma::READY.publish(&ctx)?,
        };
        let rejected: Arc<Event<PlanRejected>> = Arc::new(fpma::PLAN_REJECTED.publish(&ctx)?);
        let commands: Arc<Event<CommandRecord>> = Arc::new(fpma::COMMANDS.publish(&ctx)?);
        let _ = outlets.progress.set(&Progress::default());
        let _ = outlets.state.set(&PlanState::default());
        let _ = outlets.plan.set(&PlanGeometry::default());
        let _ = outlets.ready.set(&Readiness {
            text: "no plan loaded".into(),
            ..Readiness::default()
        });
        if self.config.start_navigation {
            tracing::warn!(
                "startNavigation is ignored: the FPMa never changes the flight state; the \
                 operator starts a loaded plan (WAYPOINT_NAVIGATION) when `ready` says so"
            );
        }
        let at = self.vas.as_str();
        let port = MareaVas {
            push: vas::PUSH_WAYPOINTS.function(&ctx, at)?,
            clear: vas::CLEAR_WAYPOINTS.function(&ctx, at)?,
            set_fence: vas::SET_FENCE.function(&ctx, at)?,
            timeout: Duration::from_millis(self.config.call_timeout_ms),
        };
        let reached = vas::WAYPOINT_REACHED.subscribe(&ctx, at)?;
        let position = vas::POSITION.subscribe(&ctx, at)?;
        let battery = vas::BATTERY.subscribe(&ctx, at)?;
        let flight_state = vas::FLIGHT_STATE.subscribe(&ctx, at)?;
        let mission_changed = vas::MISSION_CHANGED.subscribe(&ctx, at)?;
        let (tx, mut rx) = mpsc::channel::<Request>(64);
        // A plan file is loaded before the sink stores it: the sender's verdict is the load's
        // outcome (`usal send` prints the reason a plan was refused), and a refusal is raised as
        // `plan_rejected` for the stations too.
        let sink = ctx.file_sink_with(
            "plans",
            marea::FileSinkOptions {
                dir: self.config.plans_dir.clone(),
                check: Some(load_on_receipt(tx.clone(), rejected.clone())),
                ..marea::FileSinkOptions::default()
            },
        )?;
        let mut providers = Vec::new();
        for (item, replace) in [(fpma::LOAD_PLAN, false), (fpma::REPLACE_PLAN, true)] {
            providers.push(load_fn(&ctx, &tx, &commands, item, replace)?);
        }
        let t = tx.clone();
        providers.push(fpma::PLAN_GEOMETRY.provide(&ctx, move |(): ()| {
            let t = t.clone();
            async move { ask(&t, Request::Geometry).await }
        })?);
        // The progress last published, for a caller that must not miss the last one (the
        // variable is best effort: over a lossy radio its final value can be lost).
        let t = tx.clone();
        providers.push(fpma::LAST_PROGRESS.provide(&ctx, move |(): ()| {
            let t = t.clone();
            async move { ask(&t, Request::Progress).await }
        })?);
        providers.push(command_fn(
            &ctx,
            &tx,
            &commands,
            fpma::SKIP_LEG,
            |(): ()| Ok(Command::SkipLeg),
        )?);
        providers.push(command_fn(
            &ctx,
            &tx,
            &commands,
            fpma::GOTO_LEG,
            |leg: String| Ok(Command::GotoLeg(leg)),
        )?);
        providers.push(command_fn(
            &ctx,
            &tx,
            &commands,
            fpma::GOTO_STAGE,
            |s: String| parse_stage(&s).map(Command::GotoStage),
        )?);
        providers.push(command_fn(
            &ctx,
            &tx,
            &commands,
            fpma::SET_VAR,
            |a: SetVar| Ok(Command::SetVar(a.name, a.value.into())),
        )?);
        providers.push(command_fn(
            &ctx,
            &tx,
            &commands,
            fpma::HOLD_HERE,
            |a: HoldHereArgs| Ok(Command::HoldHere((&a).into())),
        )?);
        providers.push(command_fn(
            &ctx,
            &tx,
            &commands,
            fpma::EXIT_HOLD,
            |now: bool| Ok(Command::ExitHold(now)),
        )?);
        providers.push(command_fn(&ctx, &tx, &commands, fpma::PAUSE, |(): ()| {
            Ok(Command::Pause)
        })?);
        providers.push(command_fn(&ctx, &tx, &commands, fpma::RESUME, |(): ()| {
            Ok(Command::Resume)
        })?);
        providers.push(command_fn(
            &ctx,
            &tx,
            &commands,
            fpma::MODIFY_LEG,
            |a: ModifyLeg| Ok(Command::ModifyLeg(a.leg, a.changes)),
        )?);
        providers.push(command_fn(
            &ctx,
            &tx,
            &commands,
            fpma::RETASK,
            |a: Retask| {
                let points = a
                    .points
                    .iter()
                    .map(|&(lat, lon)| GeoPoint::new(lat, lon))
                    .collect();
                Ok(Command::Retask(points, a.alt, a.when.into()))
            },
        )?);
        providers.push(command_fn(
            &ctx,
            &tx,
            &commands,
            fpma::INSERT_LEGS,
            |xml: String| Ok(Command::InsertLegs(xml)),
        )?);
        providers.push(command_fn(
            &ctx,
            &tx,
            &commands,
            fpma::EMERGENCY,
            |rule: Option<String>| Ok(Command::Emergency(rule)),
        )?);

        // Files arrive loaded (see `load_on_receipt`); the sink's mailbox is only drained.
        let cx = ctx.clone();
        ctx.spawn(async move {
            loop {
                tokio::select! {
                    _ = cx.cancelled() => return,
                    f = sink.recv() => match f {
                        Ok(f) => tracing::info!("plan file {} from {} loaded", f.name, f.from),
                        Err(_) => return,
                    },
                }
            }
        });

        let core = Core::new(
            CoreConfig {
                vehicle,
                lookahead: self.config.lookahead,
            },
            port,
        );
        let mut initial = self.initial.take();
        let state_file = self.state.clone();
        let cx = ctx.clone();
        ctx.spawn(async move {
            // The function handles live as long as this task.
            let _providers = providers;
            let mut core = core;
            let persisted = state_file
                .as_ref()
                .and_then(|f| load_state(f, initial.as_ref()));
            if let Some(p) = persisted {
                // The initial plan is the one being resumed: not loaded again from its start.
                initial = None;
                core.resume(p).await;
                publish(&mut core, &outlets);
            }
            if let Some((text, source)) = initial {
                if let Err(e) = core.load(&text, &source).await {
                    tracing::error!("initial plan: {e}");
                }
                publish(&mut core, &outlets);
            }
            let mut saved = 0;
            save_state(state_file.as_ref(), &core, &mut saved).await;
            let mut last_progress: Option<(Progress, tokio::time::Instant)> = None;
            let mut retry = tokio::time::interval(Duration::from_secs(1));
            retry.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            loop {
                tokio::select! {
                    _ = cx.cancelled() => return,
                    req = rx.recv() => match req {
                        Some(Request::Load { text, source, replace, reply }) => {
                            let r = if replace {
                                core.replace(&text, &source).await
                            } else {
                                core.load(&text, &source).await
                            };
                            let _ = reply.send(r);
                        }
                        Some(Request::Command(cmd, reply)) => {
                            let r = core.command(cmd).await;
                            let _ = reply.send(r);
                        }
                        Some(Request::Geometry(reply)) => {
                            let _ = reply.send(Ok(core.geometry().clone()));
                        }
                        Some(Request::Progress(reply)) => {
                            let p = last_progress.as_ref().map(|(p, _)| p.clone()).unwrap_or_default();
                            let _ = reply.send(Ok(p));
                        }
                        None => return,
                    },
                    r = reached.recv() => match r {
                        Ok(s) => core.on_reached(s.value.seq).await,
                        Err(marea::RecvError::Closed) => return,
                        Err(e) => tracing::warn!("waypoint_reached: {e}"),
                    },
                    p = position.recv() => match p {
                        Ok(s) => core.on_position(&s.value).await,
                        Err(marea::RecvError::Closed) => return,
                        Err(e) => tracing::warn!("position: {e}"),
                    },
                    b = battery.recv() => match b {
                        Ok(s) => core.on_battery(&s.value).await,
                        Err(marea::RecvError::Closed) => return,
                        Err(e) => tracing::warn!("battery: {e}"),
                    },
                    m = mission_changed.recv() => match m {
                        Ok(m) => {
                            let items = m.value.waypoints.len() as u64;
                            core.on_mission_changed(&m.value.by, items).await;
                        }
                        Err(marea::RecvError::Closed) => return,
                        Err(e) => tracing::warn!("mission_changed: {e}"),
                    },
                    s = flight_state.recv() => match s {
                        Ok(s) => core.on_flight_state(s.value),
                        Err(marea::RecvError::Closed) => return,
                        Err(e) => tracing::warn!("flight_state: {e}"),
                    },
                    _ = retry.tick() => {
                        core.retry().await;
                        if let Some((p, at)) = &mut last_progress {
                            if at.elapsed() >= PROGRESS_REFRESH {
                                let _ = outlets.progress.set(p);
                                // "Press Start" must not be lost on a lossy link either.
                                let _ = outlets.ready.set(&core.readiness());
                                *at = tokio::time::Instant::now();
                            }
                        }
                    }
                }
                if let Some(p) = publish(&mut core, &outlets) {
                    last_progress = Some((p, tokio::time::Instant::now()));
                }
                save_state(state_file.as_ref(), &core, &mut saved).await;
            }
        });
        Ok(())
    }

    async fn stop(&mut self) -> Result<(), ServiceError> {
        Ok(())
    }
}

/// The persisted state to resume, if any: none when there is no file, when the initial plan
/// of the configuration is another one than the persisted plan (a new mission), or when the
/// file is unusable (logged, set aside: a clean start).
fn load_state(
    file: &persist::StateFile,
    initial: Option<&(String, String)>,
) -> Option<core::Persisted> {
    match file.load() {
        Ok(Some(p)) => match initial {
            Some((_, source)) if *source != p.source => {
                tracing::info!(
                    "the configured plan {source} is not the persisted one ({}): starting it",
                    p.source
                );
                None
            }
            _ => Some(p),
        },
        Ok(None) => None,
        Err(e) => {
            tracing::error!("cannot resume the persisted plan, starting clean: {e:#}");
            file.set_aside();
            None
        }
    }
}

/// Persists the core's state when it changed since the last save.
async fn save_state<V: VasPort>(
    file: Option<&persist::StateFile>,
    core: &Core<V>,
    saved: &mut u64,
) {
    let Some(file) = file else { return };
    if core.changes() == *saved {
        return;
    }
    *saved = core.changes();
    let Some(snapshot) = core.snapshot() else {
        return;
    };
    let file = file.clone();
    let r = tokio::task::spawn_blocking(move || file.save(&snapshot)).await;
    match r {
        Ok(Ok(())) => {}
        Ok(Err(e)) => tracing::error!("persisting the plan and progress: {e:#}"),
        Err(e) => tracing::error!("persisting the plan and progress: {e}"),
    }
}

/// How often an unchanged progress is published again: it is a best-effort variable, and the
/// last value before a quiet spell (a completed plan, a hold) may be lost on a radio.
const PROGRESS_REFRESH: Duration = Duration::from_secs(2);

/// Publishes what the core produced; returns the progress published, if any.
fn publish<V: VasPort>(core: &mut Core<V>, out: &Outlets) -> Option<Progress> {
    let o = core.take_outputs();
    for e in &o.events {
        if let Err(err) = out.plan_event.raise_nowait(e) {
            tracing::warn!("raising plan_event: {err}");
        }
    }
    if let Some(p) = &o.progress {
        let _ = out.progress.set(p);
    }
    if let Some(s) = &o.state {
        let _ = out.state.set(s);
    }
    if let Some(r) = &o.readiness {
        tracing::info!("{}", r.text);
        let _ = out.ready.set(r);
    }
    if let Some(g) = &o.geometry {
        if let Err(e) = out.plan.set(g) {
            tracing::warn!("publishing plan: {e}");
        }
    }
    o.progress
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn example_file_parses() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("fpma.example.xml");
        let cfg = FpmaConfig::load(&path).unwrap();
        assert_eq!(cfg, FpmaConfig::default());
    }

    #[test]
    fn unknown_attributes_and_bad_values_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("fpma.xml");
        std::fs::write(&p, r#"<fpma lookahed="5"/>"#).unwrap();
        assert!(FpmaConfig::load(&p).is_err());
        // Each refusal names the file, the line and column, and the attribute.
        std::fs::write(&p, "<fpma vas=\"vas\"\n  lookahed=\"5\"/>").unwrap();
        let e = FpmaConfig::load(&p).unwrap_err().to_string();
        assert!(
            e.contains("fpma.xml:2:3: lookahed: unknown field `lookahed`"),
            "{e}"
        );
        std::fs::write(&p, "<fpma lookahead=\"five\"/>").unwrap();
        let e = FpmaConfig::load(&p).unwrap_err().to_string();
        assert!(e.contains("fpma.xml:1:7: lookahead: "), "{e}");
        for bad in ["0", "1000000000"] {
            std::fs::write(&p, format!(r#"<fpma lookahead="{bad}"/>"#)).unwrap();
            let e = FpmaConfig::load(&p).unwrap_err().to_string();
            assert!(e.contains("lookahead must be between 1 and 1000"), "{e}");
        }
        std::fs::write(&p, r#"<fpma vehicle="aircraft" vas="rover1/vas"/>"#).unwrap();
        let cfg = FpmaConfig::load(&p).unwrap();
        assert_eq!(cfg.vehicle, VehicleKind::Aircraft);
        assert_eq!(cfg.vas_prefix(Some("uav2")), "rover1/vas");
        assert_eq!(
            FpmaConfig::default().vas_prefix(Some("rover1")),
            "rover1/vas"
        );
        assert_eq!(FpmaConfig::default().vas_prefix(None), "vas");
    }

    #[test]
    fn vehicle_parameters_come_from_the_config() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("fpma.xml");
        std::fs::write(
            &p,
            r#"<fpma vehicle="rover" minWaypointDistance="5" defaultSpeed="1.2" turnRadius="0"/>"#,
        )
        .unwrap();
        let v = FpmaConfig::load(&p).unwrap().vehicle_params().unwrap();
        assert_eq!(
            (v.min_wp_distance, v.default_speed, v.turn_radius),
            (5.0, 1.2, 0.0)
        );
        assert_eq!(v.kind, VehicleKind::Rover);
        let v = FpmaConfig::default().vehicle_params().unwrap();
        assert_eq!(v, VehicleParams::rover());
        for bad in [
            r#"<fpma minWaypointDistance="0"/>"#,
            r#"<fpma defaultSpeed="-2"/>"#,
            r#"<fpma turnRadius="NaN"/>"#,
        ] {
            std::fs::write(&p, bad).unwrap();
            let e = FpmaConfig::load(&p).unwrap_err().to_string();
            assert!(e.contains("must be a positive number"), "{bad}: {e}");
        }
    }

    #[test]
    fn stages_by_name() {
        assert_eq!(parse_stage("Approach"), Ok(Stage::Approach));
        assert!(parse_stage("cruise").unwrap_err().contains("unknown stage"));
    }
}
