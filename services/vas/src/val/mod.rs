//! The Virtual Autopilot Layer (VAL, 003 §3.1): the USAL side of the VAS, fixed whatever the
//! autopilot. It owns the flight state (with the [`transitions`] table per vehicle kind),
//! publishes telemetry and raises events on the middleware, accepts the FPMa's waypoints and
//! the FMo's manual control, and drives an [`IAutopilot`].
//!
//! Items (under `<namespace>/vas/`): see the crate README for the full list.

pub mod fence;
pub mod limits;
pub mod linkloss;
pub mod transitions;

use std::sync::{Arc, Mutex as StdMutex};
use std::time::{Duration, Instant};

use async_trait::async_trait;
use marea::{Event, IService, Service, ServiceError, Variable};
use tokio::sync::broadcast;
use usal_types::items::vas;
use usal_types::{
    Alarm, AllowedChanges, Attitude, AutopilotStatus, Battery, CommandReply, FlightState, Home,
    ManualCommand, MissionChanged, MissionTime, Position, QueueStatus, Severity, Speeds,
    StateChangeReply, StateChangeRequest, StateChanged, VehicleCommand, Waypoint, WaypointReached,
};
use usal_types::{
    CommandRecord, Failsafe, FailsafeKind, Fence, ParamValue, PoiDetection, StationHeartbeat,
};

use crate::airlog::AirLog;
use crate::apl::{ApEvent, IAutopilot};

/// The wait before asking an autopilot that refused to park again, doubled up to
/// [`PARK_RETRY_MAX`].
const PARK_RETRY_START: Duration = Duration::from_secs(1);
/// The longest wait between two attempts to park a configured autopilot.
const PARK_RETRY_MAX: Duration = Duration::from_secs(8);

/// How often the flight state, `allowed_changes` and the waypoint queue are published again
/// though unchanged.
const STATE_REFRESH: Duration = Duration::from_secs(2);

/// Settings of the VAL.
#[derive(Clone, Debug)]
pub struct ValConfig {
    /// Pattern of the manual-control variable to follow (the FMo's). Only the samples
    /// addressed to this VAS (its item prefix, e.g. `rover1/vas`) are obeyed.
    pub manual_control: String,
    /// Manual-control samples older than this are ignored, and the sticks are released when
    /// no fresh sample came for this long.
    pub manual_timeout: Duration,
    /// Period of the `mission_time` variable.
    pub mission_time_period: Duration,
    /// What `push_waypoints` accepts from the network.
    pub waypoints: limits::WaypointLimits,
    /// The stations whose manual control is obeyed: each entry is a publishing node's name
    /// or a prefix of the sample's item name (`ground` or `ground/fmo`); `None`: any station.
    pub manual_stations: Option<Vec<String>>,
    /// Manual-control samples stamped further than this ahead of our clock are refused.
    pub manual_skew: Duration,
    /// The lost-ground-link watch.
    pub link_loss: linkloss::LinkLossConfig,
    /// The vehicle's own fence: checked from the start, uploaded once the autopilot is
    /// configured (the vehicle does not start before the autopilot took it), kept for the
    /// whole flight; a plan's fence (`set_fence`) may only narrow it, and `set_fence(None)`
    /// restores it.
    pub fence: Option<Fence>,
    /// Where the air-side log is kept (`crate::airlog`), and its size bound per file.
    pub air_log: Option<(std::path::PathBuf, u64)>,
    /// Parameters set on the autopilot once it is configured, before the vehicle is parked
    /// (`vas --params`).
    pub params: Vec<crate::params_file::ParamLine>,
}

impl Default for ValConfig {
    fn default() -> Self {
        Self {
            manual_control: "**/fmo/manual_control".into(),
            manual_timeout: Duration::from_millis(500),
            mission_time_period: Duration::from_secs(1),
            waypoints: limits::WaypointLimits::default(),
            manual_stations: None,
            manual_skew: Duration::from_secs(2),
            link_loss: linkloss::LinkLossConfig::default(),
            fence: None,
            air_log: None,
            params: Vec::new(),
        }
    }
}

struct ValState {
    state: FlightState,
    /// The motors' arming as last published in `allowed_changes`.
    armed: bool,
    since: Instant,
    mission_start: Option<Instant>,
}

struct Items {
    position: Variable<Position>,
    home: Variable<Home>,
    fence: Variable<Fence>,
    attitude: Variable<Attitude>,
    speeds: Variable<Speeds>,
    battery: Variable<Battery>,
    autopilot: Variable<AutopilotStatus>,
    flight_state: Variable<FlightState>,
    mission_time: Variable<MissionTime>,
    queue: Variable<QueueStatus>,
    allowed_changes: Variable<AllowedChanges>,
    state_changed: Event<StateChanged>,
    waypoint_reached: Event<WaypointReached>,
    alarm: Event<Alarm>,
    mission_changed: Event<MissionChanged>,
    failsafe: Event<Failsafe>,
    commands: Event<CommandRecord>,
    detection: Event<PoiDetection>,
}

struct Core {
    apl: Arc<dyn IAutopilot>,
    cfg: ValConfig,
    state: StdMutex<ValState>,
    /// Serialises transitions (requests and the autopilot's own changes).
    transition: tokio::sync::Mutex<()>,
    items: Items,
    /// The fence in force: waypoints are checked against it, the autopilot enforces it.
    fence: StdMutex<Option<Fence>>,
    /// Whether the autopilot took the fence in force, and which upload said so last.
    onboard: StdMutex<(u64, fence::Onboard)>,
    /// The air-side log, when configured.
    air: Option<AirLog>,
    /// The vehicle's name, its namespace (`rover1`; empty without one): who saw a detection.
    vehicle: String,
}

use marea::sync::lock;

impl Core {
    fn state(&self) -> FlightState {
        lock(&self.state).state
    }

    /// Appends to the air-side log, when there is one.
    fn air(&self, kind: &str, fields: serde_json::Value) {
        if let Some(log) = &self.air {
            log.record(kind, fields);
        }
    }

    /// Records a command received: the `commands` event (the ground's flight log) and the
    /// air-side log, with who sent it and the answer.
    fn command_received<A: std::fmt::Debug, R: std::fmt::Debug>(
        &self,
        from: &marea::Caller,
        command: &str,
        args: &A,
        result: &Result<R, String>,
    ) {
        let rec = CommandRecord::of(from, command, args, result);
        tracing::info!(
            from = %rec.from,
            ok = rec.ok,
            "{command}({}): {}",
            rec.args,
            rec.answer
        );
        self.air(
            "command",
            serde_json::json!({"from": rec.from, "command": rec.command, "args": rec.args, "ok": rec.ok, "answer": rec.answer}),
        );
        if let Err(e) = self.items.commands.raise_nowait(&rec) {
            tracing::warn!("raising commands: {e}");
        }
    }

    fn alarm(&self, severity: Severity, text: impl Into<String>) {
        let a = Alarm {
            severity,
            text: text.into(),
        };
        self.air(
            "alarm",
            serde_json::json!({"severity": format!("{:?}", a.severity), "text": a.text}),
        );
        // Logged at the alarm's own weight: notices and information are not warnings.
        match a.severity {
            Severity::Emergency | Severity::Alert | Severity::Critical | Severity::Error => {
                tracing::error!("alarm ({:?}): {}", a.severity, a.text)
            }
            Severity::Warning => tracing::warn!("alarm ({:?}): {}", a.severity, a.text),
            Severity::Notice | Severity::Info => {
                tracing::info!("alarm ({:?}): {}", a.severity, a.text)
            }
            Severity::Debug => tracing::debug!("alarm ({:?}): {}", a.severity, a.text),
        }
        if let Err(e) = self.items.alarm.raise_nowait(&a) {
            tracing::warn!("raising alarm: {e}");
        }
    }

    /// Records a new state and tells everyone.
    fn enter(&self, to: FlightState, cause: &str) -> FlightState {
        let from = {
            let mut s = lock(&self.state);
            let from = s.state;
            s.state = to;
            s.since = Instant::now();
            let navigating = !matches!(
                to,
                FlightState::ConfigureCheck | FlightState::Parking | FlightState::Manual
            );
            if navigating && s.mission_start.is_none() {
                s.mission_start = Some(Instant::now());
            }
            from
        };
        tracing::info!("flight state {from} -> {to} ({cause})");
        self.air(
            "state",
            serde_json::json!({"from": from.to_string(), "to": to.to_string(), "cause": cause}),
        );
        let _ = self.items.flight_state.set(&to);
        self.publish_allowed();
        let ev = StateChanged {
            from,
            to,
            cause: cause.to_owned(),
        };
        if let Err(e) = self.items.state_changed.raise_nowait(&ev) {
            tracing::warn!("raising state_changed: {e}");
        }
        from
    }

    /// Publishes what may be asked from the present state (`allowed_changes`).
    fn publish_allowed(&self) {
        let (state, armed) = {
            let s = lock(&self.state);
            (s.state, s.armed)
        };
        let a = transitions::allowed_changes(self.apl.vehicle(), state, armed);
        let _ = self.items.allowed_changes.set(&a);
    }

    /// `command` (ARM, DISARM, DIRECTED): the command checker, then the autopilot.
    async fn command(&self, cmd: VehicleCommand) -> Result<CommandReply, String> {
        let _t = self.transition.lock().await;
        let from = self.state();
        let kind = self.apl.vehicle();
        let status = self.apl.status();
        if !status.connected {
            return Err(format!("{cmd} refused in {from}: autopilot not connected"));
        }
        transitions::check_command(kind, from, status.armed, &cmd)?;
        if matches!(cmd, VehicleCommand::Directed(_)) {
            lock(&self.onboard)
                .1
                .may_start(from, FlightState::Directed)?;
        }
        self.apl
            .command(cmd)
            .await
            .map_err(|e| format!("{cmd} in {from} failed: {e}"))?;
        if matches!(cmd, VehicleCommand::Directed(_)) && from != FlightState::Directed {
            self.enter(FlightState::Directed, "request");
        }
        self.note_armed(self.apl.status().armed);
        Ok(CommandReply {
            command: cmd.name().to_owned(),
            state: self.state(),
        })
    }

    /// Republishes `allowed_changes` when the motors' arming changed.
    fn note_armed(&self, armed: bool) {
        let changed = {
            let mut s = lock(&self.state);
            std::mem::replace(&mut s.armed, armed) != armed
        };
        if changed {
            self.publish_allowed();
        }
    }

    /// `change_state`: the command checker, then the autopilot.
    async fn request(&self, to: FlightState) -> Result<StateChangeReply, String> {
        let _t = self.transition.lock().await;
        let from = self.state();
        let kind = self.apl.vehicle();
        transitions::check(kind, from, to)?;
        if !self.apl.status().connected {
            return Err(format!("cannot go to {to}: autopilot not connected"));
        }
        if from == FlightState::ConfigureCheck && to != FlightState::Manual {
            return Err(format!(
                "cannot go to {to}: the autopilot is still being configured"
            ));
        }
        lock(&self.onboard).1.may_start(from, to)?;
        if to == FlightState::WaypointNavigation {
            let q = self.apl.queue_status().await.map_err(|e| e.to_string())?;
            if q.queued == 0 {
                return Err(format!(
                    "cannot go to {to}: no waypoints queued (push_waypoints first)"
                ));
            }
        }
        self.apl
            .change_state(to)
            .await
            .map_err(|e| format!("{from} -> {to} failed: {e}"))?;
        self.enter(to, "request");
        Ok(StateChangeReply { from, to })
    }

    /// Raises the `failsafe` event (and logs it).
    fn failsafe(&self, kind: FailsafeKind, action: &str, text: &str) {
        tracing::warn!("failsafe {}: {action}: {text}", kind.name());
        self.air(
            "failsafe",
            serde_json::json!({"failsafe": kind.name(), "action": action, "text": text}),
        );
        let ev = Failsafe {
            kind,
            action: action.to_owned(),
            text: text.to_owned(),
        };
        if let Err(e) = self.items.failsafe.raise_nowait(&ev) {
            tracing::warn!("raising failsafe: {e}");
        }
    }

    /// The ground link was lost: applies the configured action. Returns the state it left and
    /// the state it entered when it changed the state.
    async fn link_lost(&self, why: &str) -> Option<(FlightState, FlightState)> {
        use linkloss::LinkLossAction as A;
        let action = self.cfg.link_loss.action;
        let _t = self.transition.lock().await;
        let from = self.state();
        let moving = matches!(
            from,
            FlightState::WaypointNavigation
                | FlightState::ManualNavigation
                | FlightState::Directed
                | FlightState::TakeOff
        );
        if action == A::Continue || !moving {
            let what = if moving {
                "continuing (linkLossAction continue)"
            } else {
                "not navigating: nothing to do"
            };
            let text = format!("ground link lost: {why}; {what}");
            self.alarm(Severity::Error, &text);
            self.failsafe(FailsafeKind::LinkLost, "continue", &text);
            return None;
        }
        // A rover holds by parking (HOLD); aircraft have no hold state in the table (003
        // §3.3.1), so they return to launch. Return to launch falls back to the hold where the
        // autopilot cannot do it.
        let hold = match self.apl.vehicle() {
            usal_types::VehicleKind::Rover => FlightState::Parking,
            _ => FlightState::ReturnToLaunch,
        };
        let targets = match action {
            A::Hold => vec![hold],
            _ => vec![FlightState::ReturnToLaunch, hold],
        };
        let mut failures = Vec::new();
        for to in targets {
            if to == from {
                continue;
            }
            match self.apl.change_state(to).await {
                Ok(()) => {
                    self.enter(to, "ground link lost");
                    let name = if to == FlightState::ReturnToLaunch {
                        "rtl"
                    } else {
                        "hold"
                    };
                    let mut text = format!("ground link lost: {why}; {from} -> {to}");
                    for f in &failures {
                        text += &format!(" ({f})");
                    }
                    self.alarm(Severity::Error, &text);
                    self.failsafe(FailsafeKind::LinkLost, name, &text);
                    return Some((from, to));
                }
                Err(e) => failures.push(format!("{to} refused: {e}")),
            }
        }
        let text = format!(
            "ground link lost: {why}; the {} action failed: {}",
            action.name(),
            failures.join("; ")
        );
        self.alarm(Severity::Critical, &text);
        self.failsafe(FailsafeKind::LinkLost, "failed", &text);
        None
    }

    /// The ground link is back after `outage`; `taken` is what [`Core::link_lost`] did.
    async fn link_restored(&self, outage: Duration, taken: Option<(FlightState, FlightState)>) {
        let mut text = format!(
            "ground link restored after {:.1} s of silence",
            outage.as_secs_f64()
        );
        let mut action = "none";
        if let Some((before, set)) = taken {
            let _t = self.transition.lock().await;
            let now = self.state();
            match self.cfg.link_loss.recovery {
                _ if now != set => {
                    text += &format!("; the state changed meanwhile ({now}): left as it is");
                }
                linkloss::LinkRecovery::Wait => {
                    action = "wait";
                    text += &format!(
                        "; staying in {now} until the operator decides (linkRecovery wait)"
                    );
                }
                linkloss::LinkRecovery::Resume => match self.apl.change_state(before).await {
                    Ok(()) => {
                        action = "resume";
                        self.enter(before, "ground link restored");
                        text += &format!("; resuming {before}");
                    }
                    Err(e) => {
                        action = "failed";
                        text += &format!("; cannot resume {before}: {e}");
                    }
                },
            }
        }
        self.alarm(Severity::Info, &text);
        self.failsafe(FailsafeKind::LinkRestored, action, &text);
    }

    /// Uploads the fence in force (at start, after the autopilot reconnected, when a plan
    /// brings its own) and records whether the autopilot took it: a vehicle whose fence the
    /// autopilot refused does not start, and an alarm says why.
    ///
    /// # Errors
    /// The autopilot's refusal, as the alarm says it.
    async fn upload_fence(&self) -> Result<(), String> {
        let (generation, f) = {
            let mut o = lock(&self.onboard);
            let f = lock(&self.fence).clone();
            o.0 += 1;
            o.1 = fence::Onboard::initial(f.as_ref());
            (o.0, f)
        };
        let result = self.apl.upload_fence(f.as_ref()).await;
        let (outcome, answer) = match (&f, result) {
            (Some(_), Ok(())) => (fence::Onboard::Taken, Ok(())),
            (None, Ok(())) => (fence::Onboard::NoFence, Ok(())),
            (Some(_), Err(e)) => {
                let text = format!(
                    "the autopilot did not take the fence: {e}; the vehicle will not start until it does"
                );
                (fence::Onboard::Refused(e.to_string()), Err(text))
            }
            // Clearing failed: whatever the autopilot still keeps only holds it tighter.
            (None, Err(e)) => (
                fence::Onboard::NoFence,
                Err(format!("the autopilot did not clear its fence: {e}")),
            ),
        };
        {
            // A later upload (another plan's fence) has the last word.
            let mut o = lock(&self.onboard);
            if o.0 == generation {
                o.1 = outcome;
            }
        }
        if let Err(text) = &answer {
            self.alarm(
                if f.is_some() {
                    Severity::Critical
                } else {
                    Severity::Warning
                },
                text,
            );
        }
        answer
    }

    /// `set_fence`: a plan's fence narrows the vehicle's (`None`: the vehicle's alone), is
    /// uploaded to the autopilot and kept for the waypoint checks.
    ///
    /// # Errors
    /// A fence that is not one, or that reaches outside the vehicle's fence: nothing changes.
    /// An autopilot that does not take it is not an error of the plan: the answer says so,
    /// an alarm is raised and the vehicle does not start.
    async fn set_fence(&self, f: Option<Fence>) -> Result<String, String> {
        let vehicle = self.cfg.fence.as_ref();
        let f = match f {
            Some(f) if f.is_empty() => vehicle.cloned(),
            Some(f) => {
                f.validate().map_err(|e| format!("fence refused: {e}"))?;
                match vehicle {
                    Some(v) => Some(
                        v.narrowed_by(&f)
                            .map_err(|e| format!("fence refused: {e}"))?,
                    ),
                    None => Some(f),
                }
            }
            None => vehicle.cloned(),
        };
        *lock(&self.fence) = f.clone();
        self.publish_fence();
        match self.upload_fence().await {
            Ok(()) => Ok(match (&f, vehicle) {
                (Some(_), Some(_)) => "fence in force (the vehicle's, narrowed by the plan's where it sets one) uploaded to the autopilot".to_owned(),
                (Some(_), None) => "fence set and uploaded to the autopilot".to_owned(),
                (None, _) => "fence cleared".to_owned(),
            }),
            Err(text) => Ok(text),
        }
    }

    /// Publishes the fence in force for the stations' maps (an empty fence: none).
    fn publish_fence(&self) {
        let f = lock(&self.fence).clone().unwrap_or_default();
        let _ = self.items.fence.set(&f);
    }

    async fn publish_queue(&self) {
        if let Ok(q) = self.apl.queue_status().await {
            let _ = self.items.queue.set(&q);
        }
    }

    async fn on_ap(&self, ev: ApEvent) {
        match ev {
            ApEvent::Position(p) => drop(self.items.position.set(&p)),
            ApEvent::Home(h) => drop(self.items.home.set(&h)),
            ApEvent::Detection(mut d) => {
                d.by.clone_from(&self.vehicle);
                if let Err(e) = self.items.detection.raise_nowait(&d) {
                    tracing::warn!("raising detection: {e}");
                }
            }
            ApEvent::Attitude(a) => drop(self.items.attitude.set(&a)),
            ApEvent::Speeds(s) => drop(self.items.speeds.set(&s)),
            ApEvent::Battery(b) => drop(self.items.battery.set(&b)),
            ApEvent::Status(s) => {
                self.note_armed(s.armed);
                let _ = self.items.autopilot.set(&s);
            }
            ApEvent::WaypointReached(w) => {
                if let Err(e) = self.items.waypoint_reached.raise_nowait(&w) {
                    tracing::warn!("raising waypoint_reached: {e}");
                }
                self.publish_queue().await;
            }
            ApEvent::Alarm(a) => {
                // The autopilot's own fence breach (ArduPilot "... fence breached", mavsim
                // "Fence breached: ..."): a failsafe the stations list.
                let lower = a.text.to_ascii_lowercase();
                if lower.contains("fence") && lower.contains("breach") {
                    self.failsafe(FailsafeKind::Fence, "autopilot", &a.text);
                }
                self.alarm(a.severity, a.text);
            }
            ApEvent::ModeChanged { mode, state } => {
                let _t = self.transition.lock().await;
                match state {
                    // Until configured, the autopilot's own mode means nothing to USAL.
                    _ if self.state() == FlightState::ConfigureCheck => {}
                    Some(to) if to != self.state() => {
                        self.enter(to, &format!("autopilot mode {mode}"));
                    }
                    Some(_) => {}
                    None => self.alarm(
                        Severity::Warning,
                        format!(
                            "autopilot switched to {mode}, which no {} state matches",
                            self.state()
                        ),
                    ),
                }
            }
            ApEvent::Landed => {
                let _t = self.transition.lock().await;
                let from = self.state();
                if matches!(
                    from,
                    FlightState::Parking | FlightState::Manual | FlightState::ConfigureCheck
                ) {
                    return;
                }
                match self.apl.change_state(FlightState::Parking).await {
                    Ok(()) => {
                        self.enter(FlightState::Parking, "landed and disarmed");
                    }
                    Err(e) => self.alarm(
                        Severity::Warning,
                        format!("landed and disarmed in {from}, but cannot park: {e}"),
                    ),
                }
            }
            // Parking after the configuration is asked again until the autopilot accepts
            // (`park_when_configured`, beside the event loop).
            ApEvent::Configured => {}
            ApEvent::MissionChanged(m) => {
                self.air(
                    "mission",
                    serde_json::json!({"op": "written by another station", "by": m.by, "items": m.waypoints.len()}),
                );
                if let Err(e) = self.items.mission_changed.raise_nowait(&m) {
                    tracing::warn!("raising mission_changed: {e}");
                }
                self.publish_queue().await;
            }
            ApEvent::LinkLost | ApEvent::LinkRestored => {
                let _ = self.items.autopilot.set(&self.apl.status());
            }
        }
    }

    /// Sets a parameter for the operator: not while the autopilot is still being configured.
    async fn set_param(&self, p: &ParamValue) -> Result<ParamValue, String> {
        if self.state() == FlightState::ConfigureCheck {
            return Err(format!(
                "set_param {} refused in CONFIGURE_CHECK: the autopilot is still being configured",
                p.name
            ));
        }
        let value = self
            .apl
            .set_param(&p.name, p.value)
            .await
            .map_err(|e| e.to_string())?;
        Ok(ParamValue {
            name: p.name.clone(),
            value,
        })
    }

    /// Uploads the start-up parameters (`vas --params`), each checked against what the
    /// autopilot echoes; each refusal is an alarm, and a summary says how many took.
    async fn upload_params(&self) {
        let params = &self.cfg.params;
        if params.is_empty() {
            return;
        }
        let mut refused = 0usize;
        for p in params {
            if let Err(e) = self.apl.set_param(&p.name, p.value).await {
                refused += 1;
                self.alarm(
                    Severity::Warning,
                    format!(
                        "start-up parameter {} = {} (line {}) refused: {e}",
                        p.name, p.value, p.line
                    ),
                );
            }
        }
        let severity = if refused == 0 {
            Severity::Info
        } else {
            Severity::Warning
        };
        self.alarm(
            severity,
            format!(
                "start-up parameters: {} of {} set and verified",
                params.len() - refused,
                params.len()
            ),
        );
    }

    /// CONFIGURE_CHECK is over: parks the vehicle. An autopilot that refuses (its own checks
    /// still running: TEMPORARILY_REJECTED past the manager's own retries, a mode it will not
    /// enter yet) is asked again with a growing delay, for as long as it takes; each new reason
    /// is an alarm, so the stations and `usal run` say why the vehicle is not ready.
    async fn park_when_configured(&self) {
        let mut wait = PARK_RETRY_START;
        let mut last: Option<String> = None;
        for attempt in 1u32.. {
            {
                let _t = self.transition.lock().await;
                if self.state() != FlightState::ConfigureCheck {
                    return;
                }
                match self.apl.change_state(FlightState::Parking).await {
                    Ok(()) => {
                        let cause = if attempt == 1 {
                            "autopilot configured".to_owned()
                        } else {
                            format!("autopilot configured (parked at attempt {attempt})")
                        };
                        self.enter(FlightState::Parking, &cause);
                        if last.is_some() {
                            self.alarm(
                                Severity::Info,
                                format!("the autopilot accepted at attempt {attempt}: parked"),
                            );
                        }
                        return;
                    }
                    Err(e) => {
                        let text = e.to_string();
                        if last.as_deref() == Some(text.as_str()) {
                            tracing::info!("still cannot park (attempt {attempt}): {text}");
                        } else {
                            self.alarm(
                                Severity::Error,
                                format!(
                                    "cannot park: {text}; the vehicle stays in CONFIGURE_CHECK and the VAS asks again until the autopilot accepts"
                                ),
                            );
                        }
                        last = Some(text);
                    }
                }
            }
            tokio::time::sleep(wait).await;
            wait = (wait * 2).min(PARK_RETRY_MAX);
        }
    }

    fn mission_time(&self) -> MissionTime {
        let s = lock(&self.state);
        MissionTime {
            elapsed: s.mission_start.map_or(0.0, |t| t.elapsed().as_secs_f64()),
            in_state: s.since.elapsed().as_secs_f64(),
        }
    }
}

/// The VAS as a middleware service (`vas`): the VAL over an [`IAutopilot`].
pub struct Vas {
    apl: Arc<dyn IAutopilot>,
    cfg: ValConfig,
}

impl Vas {
    /// A VAS driving `apl`.
    pub fn new(apl: Arc<dyn IAutopilot>, cfg: ValConfig) -> Self {
        Self { apl, cfg }
    }
}

#[async_trait]
impl IService for Vas {
    fn name(&self) -> &str {
        "vas"
    }

    async fn start(&mut self, ctx: Service) -> Result<(), ServiceError> {
        let items = Items {
            position: vas::POSITION.publish(&ctx)?,
            home: vas::HOME.publish(&ctx)?,
            fence: vas::FENCE.publish(&ctx)?,
            attitude: vas::ATTITUDE.publish(&ctx)?,
            speeds: vas::SPEEDS.publish(&ctx)?,
            battery: vas::BATTERY.publish(&ctx)?,
            autopilot: vas::AUTOPILOT.publish(&ctx)?,
            flight_state: vas::FLIGHT_STATE.publish(&ctx)?,
            mission_time: vas::MISSION_TIME.publish(&ctx)?,
            queue: vas::QUEUE.publish(&ctx)?,
            allowed_changes: vas::ALLOWED_CHANGES.publish(&ctx)?,
            state_changed: vas::STATE_CHANGED.publish(&ctx)?,
            waypoint_reached: vas::WAYPOINT_REACHED.publish(&ctx)?,
            alarm: vas::ALARM.publish(&ctx)?,
            mission_changed: vas::MISSION_CHANGED.publish(&ctx)?,
            failsafe: vas::FAILSAFE.publish(&ctx)?,
            commands: vas::COMMANDS.publish(&ctx)?,
            detection: vas::DETECTION.publish(&ctx)?,
        };
        let air = match &self.cfg.air_log {
            None => None,
            Some((dir, max)) => match AirLog::open(dir, *max) {
                Ok(log) => Some(log),
                Err(e) => {
                    // Flying without it beats not flying; the alarm says so once connected.
                    tracing::error!(
                        "air log {}: {e}: not logging on the air side",
                        dir.display()
                    );
                    None
                }
            },
        };
        let core = Arc::new(Core {
            apl: self.apl.clone(),
            cfg: self.cfg.clone(),
            state: StdMutex::new(ValState {
                state: FlightState::ConfigureCheck,
                armed: false,
                since: Instant::now(),
                mission_start: None,
            }),
            transition: tokio::sync::Mutex::new(()),
            items,
            vehicle: {
                let me = ctx.full_name("");
                let me = me.trim_end_matches('/');
                me.strip_suffix("vas")
                    .unwrap_or(me)
                    .trim_end_matches('/')
                    .to_owned()
            },
            fence: StdMutex::new(self.cfg.fence.clone()),
            onboard: StdMutex::new((0, fence::Onboard::initial(self.cfg.fence.as_ref()))),
            air,
        });
        let _ = core.items.flight_state.set(&FlightState::ConfigureCheck);
        let _ = core.items.queue.set(&QueueStatus::default());
        core.publish_fence();
        core.publish_allowed();

        let c = core.clone();
        let change = vas::CHANGE_STATE.provide_with_caller(
            &ctx,
            move |req: StateChangeRequest, from: marea::Caller| {
                let c = c.clone();
                async move {
                    let r = c.request(req.to).await;
                    c.command_received(&from, "change_state", &req.to, &r);
                    r
                }
            },
        )?;
        let c = core.clone();
        let command = vas::COMMAND.provide_with_caller(
            &ctx,
            move |cmd: VehicleCommand, from: marea::Caller| {
                let c = c.clone();
                async move {
                    let r = c.command(cmd).await;
                    c.command_received(&from, "command", &cmd, &r);
                    r
                }
            },
        )?;
        let c = core.clone();
        let allowed = vas::ALLOWED_STATES.provide(&ctx, move |(): ()| {
            let c = c.clone();
            async move {
                let kind = c.apl.vehicle();
                let from = c.state();
                Ok::<Vec<FlightState>, String>(transitions::allowed(kind, from))
            }
        })?;
        let c = core.clone();
        let push = vas::PUSH_WAYPOINTS.provide(&ctx, move |wps: Vec<Waypoint>| {
            let c = c.clone();
            async move {
                // Checked before anything reaches the autopilot; refused whole. The queue's
                // room is checked by the APL as it queues them (one step).
                c.cfg.waypoints.check(&wps)?;
                if let Some(f) = lock(&c.fence).as_ref() {
                    if let Err(e) = fence::check_waypoints(f, &wps) {
                        c.failsafe(FailsafeKind::Fence, "refused", &e);
                        return Err(e);
                    }
                }
                let (count, seqs) = (
                    wps.len(),
                    (wps.first().map(|w| w.seq), wps.last().map(|w| w.seq)),
                );
                let r = c
                    .apl
                    .push_waypoints(wps, c.cfg.waypoints.max_queued)
                    .await
                    .map_err(|e| e.to_string());
                c.air(
                    "mission",
                    serde_json::json!({"op": "push", "count": count, "first_seq": seqs.0, "last_seq": seqs.1,
                        "ok": r.is_ok(), "answer": r.as_ref().map_or_else(|e| e.clone(), |q| format!("{q:?}"))}),
                );
                let q = r?;
                let _ = c.items.queue.set(&q);
                Ok(q)
            }
        })?;
        let c = core.clone();
        let clear = vas::CLEAR_WAYPOINTS.provide(&ctx, move |(): ()| {
            let c = c.clone();
            async move {
                let r = c.apl.clear_waypoints().await.map_err(|e| e.to_string());
                c.air(
                    "mission",
                    serde_json::json!({"op": "clear", "ok": r.is_ok(),
                        "answer": r.as_ref().map_or_else(|e| e.clone(), |q| format!("{q:?}"))}),
                );
                let q = r?;
                let _ = c.items.queue.set(&q);
                Ok(q)
            }
        })?;
        let c = core.clone();
        let set_fence = vas::SET_FENCE.provide_with_caller(
            &ctx,
            move |f: Option<Fence>, from: marea::Caller| {
                let c = c.clone();
                async move {
                    let r = c.set_fence(f.clone()).await;
                    c.command_received(&from, "set_fence", &f, &r);
                    r
                }
            },
        )?;
        // The autopilot's parameters: read, set (logged as a command, like every change), listed.
        let c = core.clone();
        let get_param = vas::GET_PARAM.provide(&ctx, move |name: String| {
            let c = c.clone();
            async move {
                let value = c.apl.get_param(&name).await.map_err(|e| e.to_string())?;
                Ok::<ParamValue, String>(ParamValue { name, value })
            }
        })?;
        let c = core.clone();
        let set_param = vas::SET_PARAM.provide_with_caller(
            &ctx,
            move |p: ParamValue, from: marea::Caller| {
                let c = c.clone();
                async move {
                    let r = c.set_param(&p).await;
                    c.command_received(&from, "set_param", &p, &r);
                    r
                }
            },
        )?;
        let c = core.clone();
        let list_params = vas::LIST_PARAMS.provide(&ctx, move |(): ()| {
            let c = c.clone();
            async move {
                let all = c.apl.list_params().await.map_err(|e| e.to_string())?;
                Ok::<Vec<ParamValue>, String>(
                    all.into_iter()
                        .map(|(name, value)| ParamValue { name, value })
                        .collect(),
                )
            }
        })?;
        // Part of the mission on board, as the autopilot holds it (a partial read).
        let c = core.clone();
        let read_mission = vas::READ_MISSION.provide(&ctx, move |(first, last): (u16, u16)| {
            let c = c.clone();
            async move {
                c.apl
                    .read_mission(first, last)
                    .await
                    .map_err(|e| format!("reading mission items {first}..={last}: {e}"))
            }
        })?;
        let manual = ctx.subscribe_variable::<ManualCommand>(&core.cfg.manual_control)?;
        // This VAS's item prefix, the address a manual command must carry to be obeyed.
        let me = ctx.full_name("").trim_end_matches('/').to_owned();

        // ListenAp, retried until the autopilot answers.
        let c = core.clone();
        let cx = ctx.clone();
        ctx.spawn(async move {
            loop {
                let r = tokio::select! {
                    _ = cx.cancelled() => return,
                    r = c.apl.listen_ap() => r,
                };
                match r {
                    Ok(()) => return,
                    Err(e) => c.alarm(Severity::Error, format!("autopilot: {e}")),
                }
            }
        });

        // Autopilot events -> VAL.
        let c = core.clone();
        let cx = ctx.clone();
        let mut events = core.apl.events();
        ctx.spawn(async move {
            loop {
                tokio::select! {
                    _ = cx.cancelled() => return,
                    ev = events.recv() => match ev {
                        Ok(ev @ (ApEvent::Configured | ApEvent::LinkRestored)) => {
                            let configured = matches!(ev, ApEvent::Configured);
                            c.on_ap(ev).await;
                            // Beside the event loop: a configured autopilot is parked (asked
                            // again until it accepts), then the fence goes up before the
                            // vehicle may start, and again to a restarted (reconnected)
                            // autopilot, which may have lost it (a few parameters and a
                            // transfer).
                            let c2 = c.clone();
                            let cx2 = cx.clone();
                            cx.spawn(async move {
                                tokio::select! {
                                    () = cx2.cancelled() => {}
                                    () = async {
                                        if configured {
                                            // The start-up parameters go up before the
                                            // vehicle is parked (and so before it may start).
                                            c2.upload_params().await;
                                            c2.park_when_configured().await;
                                        }
                                        if lock(&c2.fence).is_some() {
                                            let _ = c2.upload_fence().await;
                                        }
                                    } => {}
                                }
                            });
                        }
                        Ok(ev) => c.on_ap(ev).await,
                        Err(broadcast::error::RecvError::Lagged(n)) => {
                            tracing::warn!("VAL lagged {n} autopilot events");
                        }
                        Err(broadcast::error::RecvError::Closed) => return,
                    },
                }
            }
        });

        // Manual control: only what is addressed to this vehicle; newest wins, stale samples
        // ignored, sticks released on silence (also when the station drives another vehicle).
        let c = core.clone();
        let cx = ctx.clone();
        ctx.spawn(async move {
            let timeout = c.cfg.manual_timeout;
            let mut last: Option<(u64, Instant)> = None;
            let mut released = true;
            let mut refused = ManualRefusals::default();
            let mut tick = tokio::time::interval((timeout / 2).max(Duration::from_millis(10)));
            loop {
                tokio::select! {
                    _ = cx.cancelled() => return,
                    s = manual.recv() => match s {
                        Ok(s) => {
                            // Another vehicle's sticks: not ours to obey, and their timestamps
                            // must not order ours (another station's clock may be ahead).
                            if !s.value.is_for(&me) {
                                continue;
                            }
                            // Only from a configured station, never from the far future.
                            let stamp = s.value.sticks.timestamp_ms;
                            let admitted =
                                c.cfg.manual_admits(&s.publisher, &s.name, stamp, unix_ms());
                            if let Err(why) = admitted {
                                refused.refuse(&c, &s.publisher, &why);
                                continue;
                            }
                            let sticks = s.value.sticks;
                            let before = last.map(|(ts, at)| {
                                (ts, s.received.saturating_duration_since(at))
                            });
                            let age = s.received.elapsed();
                            if !takes_manual_sample(before, sticks.timestamp_ms, age, timeout) {
                                continue;
                            }
                            last = Some((sticks.timestamp_ms, s.received));
                            let state = c.state();
                            if matches!(state, FlightState::ManualNavigation | FlightState::Taxi) {
                                released = false;
                                let sticks = if state == FlightState::Taxi {
                                    taxi_sticks(sticks)
                                } else {
                                    sticks
                                };
                                if let Err(e) = c.apl.manual_navigation(Some(sticks)).await {
                                    tracing::debug!("manual control: {e}");
                                }
                            }
                        }
                        Err(e) => {
                            tracing::warn!("manual control: {e}");
                            return;
                        }
                    },
                    _ = tick.tick() => {
                        let stale = last.is_none_or(|(_, at)| at.elapsed() > timeout);
                        if stale && !released {
                            released = true;
                            let _ = c.apl.manual_navigation(None).await;
                            if matches!(c.state(), FlightState::ManualNavigation | FlightState::Taxi) {
                                c.alarm(Severity::Warning, "manual control stale: sticks released");
                            }
                        }
                    }
                }
            }
        });

        // Lost ground link: the station's heartbeat and the radio's health.
        let heartbeat =
            ctx.subscribe_variable::<StationHeartbeat>(&core.cfg.link_loss.heartbeat)?;
        let radio = match &core.cfg.link_loss.radio_link {
            Some(link) => {
                let me = ctx.full_name("");
                let ns = me.trim_end_matches('/').rsplit_once('/').map(|(ns, _)| ns);
                let name = match ns {
                    Some(ns) => format!("{ns}/link/{link}/stats"),
                    None => format!("link/{link}/stats"),
                };
                Some(ctx.subscribe_variable::<marea::LinkHealth>(&name)?)
            }
            None => None,
        };
        let c = core.clone();
        let cx = ctx.clone();
        ctx.spawn(async move {
            let cfg = &c.cfg.link_loss;
            let mut watch = linkloss::LinkWatch::new(cfg.timeout);
            let mut taken = None;
            let mut heard = false;
            let mut tick = tokio::time::interval((cfg.timeout / 10).max(Duration::from_millis(50)));
            tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
            let mut radio = radio;
            loop {
                tokio::select! {
                    _ = cx.cancelled() => return,
                    h = heartbeat.recv() => match h {
                        Ok(h) => {
                            if !heard {
                                heard = true;
                                tracing::info!(
                                    "ground link watch armed: heartbeat of {} ({})",
                                    h.value.station,
                                    h.publisher
                                );
                            }
                            watch.heartbeat(h.received);
                        }
                        Err(e) => {
                            tracing::warn!("station heartbeat: {e}");
                            return;
                        }
                    },
                    r = async { radio.as_mut().expect("guarded").recv().await }, if radio.is_some() => match r {
                        Ok(r) => watch.radio(r.received, &r.value.link, r.value.peers),
                        Err(e) => {
                            tracing::warn!("radio health: {e}");
                            radio = None;
                        }
                    },
                    _ = tick.tick() => {}
                }
                match watch.poll(Instant::now()) {
                    Some(linkloss::Decision::Lost { why }) => taken = c.link_lost(&why).await,
                    Some(linkloss::Decision::Restored { outage }) => {
                        c.link_restored(outage, taken.take()).await;
                    }
                    None => {}
                }
            }
        });

        // Mission time; the function handles live as long as this task.
        let c = core;
        let cx = ctx.clone();
        ctx.spawn(async move {
            let _handles = (change, command, allowed, push, clear, set_fence);
            let _params = (get_param, set_param, list_params, read_mission);
            let mut tick =
                tokio::time::interval(c.cfg.mission_time_period.max(Duration::from_millis(10)));
            // The flight state, what may be asked from it and the waypoint queue are published
            // on change only, best effort; a change lost (a lossy radio, a busy host's full
            // socket buffer) would leave a station showing an old state (and offering the
            // wrong buttons), or a fleet waiting for waypoints it already queued, until the
            // next change: repeat them now and then.
            let mut refresh = tokio::time::interval(STATE_REFRESH);
            loop {
                tokio::select! {
                    _ = cx.cancelled() => return,
                    _ = tick.tick() => drop(c.items.mission_time.set(&c.mission_time())),
                    _ = refresh.tick() => {
                        let _ = c.items.flight_state.set(&c.state());
                        c.publish_allowed();
                        c.publish_queue().await;
                    }
                }
            }
        });
        Ok(())
    }

    async fn stop(&mut self) -> Result<(), ServiceError> {
        self.apl.shutdown().await;
        Ok(())
    }
}

impl ValConfig {
    /// Whether a manual-control sample published by node `publisher` as item `name`, stamped
    /// `timestamp_ms` (our clock reading `now_ms`), comes from a configured station and not
    /// from the far future.
    ///
    /// # Errors
    /// Why it is refused.
    pub fn manual_admits(
        &self,
        publisher: &str,
        name: &str,
        timestamp_ms: u64,
        now_ms: u64,
    ) -> Result<(), String> {
        if let Some(allowed) = &self.manual_stations {
            let ok = allowed.iter().any(|a| {
                a == publisher
                    || name
                        .strip_prefix(a.as_str())
                        .is_some_and(|rest| rest.starts_with('/'))
            });
            if !ok {
                return Err(format!(
                    "manual control from node {publisher} ({name}) refused: not a configured station"
                ));
            }
        }
        let skew = u64::try_from(self.manual_skew.as_millis()).unwrap_or(u64::MAX);
        if timestamp_ms > now_ms.saturating_add(skew) {
            return Err(format!(
                "manual control from node {publisher} refused: stamped {} ms ahead of our clock",
                timestamp_ms - now_ms
            ));
        }
        Ok(())
    }
}

/// Our clock as the stations stamp their samples: ms since the Unix epoch.
fn unix_ms() -> u64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| u64::try_from(d.as_millis()).unwrap_or(u64::MAX))
}

/// Refused manual-control samples: counted, logged and raised as an alarm at most once a
/// minute per publishing node, so a flood does not flood the alarms.
#[derive(Default)]
struct ManualRefusals {
    count: u64,
    last_told: std::collections::HashMap<String, Instant>,
}

impl ManualRefusals {
    const QUIET: Duration = Duration::from_secs(60);

    fn refuse(&mut self, core: &Core, publisher: &str, why: &str) {
        self.count += 1;
        let due = self
            .last_told
            .get(publisher)
            .is_none_or(|t| t.elapsed() >= Self::QUIET);
        // Bounded: a forger inventing node names cannot grow the map past this.
        if due && (self.last_told.len() < 256 || self.last_told.contains_key(publisher)) {
            self.last_told.insert(publisher.to_owned(), Instant::now());
            tracing::warn!("{why} ({} refused so far)", self.count);
            core.alarm(
                Severity::Warning,
                format!("{why} ({} refused so far)", self.count),
            );
        }
    }
}

/// Whether a manual-control sample stamped `timestamp_ms` by its station, which arrived
/// `age` ago, is obeyed after the last one obeyed (`last`: its stamp and how long before this
/// one it arrived).
///
/// Newest wins, but only among live samples: once the last one is older than `timeout` any
/// fresh sample is taken whatever its stamp. A sample stamped far in the future (a station
/// whose clock jumped, or a forged `u64::MAX`) would otherwise refuse every later one until
/// the VAS restarted.
fn takes_manual_sample(
    last: Option<(u64, Duration)>,
    timestamp_ms: u64,
    age: Duration,
    timeout: Duration,
) -> bool {
    let newer = last.is_none_or(|(ts, before)| timestamp_ms > ts || before > timeout);
    age <= timeout && newer
}

/// Most throttle a taxiing plane gets (of full): ground speed, never take-off speed.
pub const TAXI_THROTTLE: f32 = 0.3;

/// The station's sticks as a taxiing plane obeys them: steering as given, the throttle capped
/// at [`TAXI_THROTTLE`], no pitch (it stays on its wheels).
pub fn taxi_sticks(mut mc: usal_types::ManualControl) -> usal_types::ManualControl {
    mc.throttle = if mc.throttle.is_finite() {
        mc.throttle.clamp(0.0, TAXI_THROTTLE)
    } else {
        0.0
    };
    mc.pitch = 0.0;
    mc
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_taxiing_plane_gets_a_capped_throttle_and_no_pitch() {
        let mc = |throttle, pitch| usal_types::ManualControl {
            roll: 0.5,
            pitch,
            throttle,
            yaw: -0.2,
            timestamp_ms: 7,
        };
        let t = taxi_sticks(mc(1.0, 0.8));
        assert_eq!(
            (t.throttle, t.pitch, t.roll, t.yaw),
            (TAXI_THROTTLE, 0.0, 0.5, -0.2)
        );
        assert_eq!(taxi_sticks(mc(0.1, 0.0)).throttle, 0.1);
        assert_eq!(taxi_sticks(mc(-1.0, 0.0)).throttle, 0.0);
        assert_eq!(taxi_sticks(mc(f32::NAN, 0.0)).throttle, 0.0);
    }

    #[test]
    fn a_sample_stamped_in_the_far_future_orders_the_others_only_while_it_is_live() {
        let ms = Duration::from_millis;
        let timeout = ms(500);
        let take = |last, stamp, age, before| {
            takes_manual_sample(Some((last, before)), stamp, age, timeout)
        };
        // A forged stamp refuses older ones while it is live...
        assert!(!take(u64::MAX, 1_000, ms(0), ms(100)));
        // ...and once it is stale, the real station is obeyed again.
        assert!(take(u64::MAX, 1_000, ms(0), ms(600)));
        // Among live samples, newest wins.
        assert!(!take(2_000, 1_999, ms(0), ms(10)));
        assert!(take(2_000, 2_001, ms(0), ms(10)));
        // A sample that waited longer than the timeout is stale whatever its stamp.
        assert!(!take(2_000, 2_001, ms(501), ms(10)));
        assert!(takes_manual_sample(None, 0, ms(0), timeout));
    }

    #[test]
    fn manual_control_only_from_configured_stations_and_not_from_the_future() {
        let open = ValConfig::default();
        let now = 1_000_000;
        assert!(open
            .manual_admits("x", "x/fmo/manual_control", now, now)
            .is_ok());
        let cfg = ValConfig {
            manual_stations: Some(vec!["ground-fmo".into(), "base/fmo".into()]),
            ..ValConfig::default()
        };
        // By node name, or by the item's prefix.
        assert!(cfg
            .manual_admits("ground-fmo", "fmo/manual_control", now, now)
            .is_ok());
        assert!(cfg
            .manual_admits("other", "base/fmo/manual_control", now, now)
            .is_ok());
        let e = cfg
            .manual_admits("intruder", "evil/fmo/manual_control", now, now)
            .unwrap_err();
        assert!(
            e.contains("node intruder") && e.contains("not a configured station"),
            "{e}"
        );
        // A prefix must end at a segment boundary.
        assert!(cfg
            .manual_admits("x", "base/fmox/manual_control", now, now)
            .is_err());
        // Within the skew is fine, beyond it (u64::MAX included) refused.
        assert!(cfg
            .manual_admits("ground-fmo", "f", now + 2_000, now)
            .is_ok());
        let e = cfg
            .manual_admits("ground-fmo", "f", now + 2_001, now)
            .unwrap_err();
        assert!(e.contains("2001 ms ahead"), "{e}");
        assert!(cfg.manual_admits("ground-fmo", "f", u64::MAX, now).is_err());
    }
}
