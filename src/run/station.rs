//! The ground station run inside the launcher: it joins the mission's network, uploads the
//! flight plan to the FPMa as a file, follows the plan's progress and the vehicle's state, has
//! the FPMa re-send its queue when the VAS comes back after a restart, and sums the flight up.
//! It presses Start itself only when the mission says so (`<station start="auto">`); with
//! `start="operator"` the pilot does, after a VAS restart too.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use flightplan::api::items as fpma;
use flightplan::api::{PlanEventKind, Progress};
use marea::{NetworkConfig, Node, SendFileOptions};
use serde_json::json;
use tokio::sync::broadcast;
use tokio::time::Instant;
use tokio_util::sync::CancellationToken;
use usal_types::items::vas;
use usal_types::{AllowedChanges, FlightState, Position, StateChangeRequest};

use super::failsafe::{self, FailsafeNote};
use super::mission::StartBy;
use flightplan::aircraft::{self, AircraftPlan, AircraftSummary, FlightRecord};

use super::supervisor::Notice;
use super::ui::{self, Ui};

/// How long the plan upload keeps looking for the FPMa.
const SEND_RETRY: Duration = Duration::from_secs(120);
/// Time limit of the calls the station makes.
const CALL_TIMEOUT: Duration = Duration::from_secs(5);
/// Least time between two attempts to bring a restarted VAS back into the plan.
const RETRY: Duration = Duration::from_secs(1);
/// Upload the plan after this long even if the VAS never reports a configured autopilot.
const UPLOAD_ANYWAY: Duration = Duration::from_secs(30);
/// A loaded plan whose vehicle stays parked this long gets WAYPOINT_NAVIGATION asked for when
/// the mission makes `usal run` the one who presses Start (`start="auto"`; the FPMa never
/// changes the flight state); asked again this long after a refusal.
const KICK_AFTER: Duration = Duration::from_secs(1);
/// How long completion waits for the last reports once the plan says it is done.
const SETTLE: Duration = Duration::from_secs(2);
/// How long to wait for the progress variable to confirm a completion the FPMa's event
/// announced (the FPMa repeats an unchanged progress every 2 s).
const SETTLE_ON_EVENT: Duration = Duration::from_secs(10);

/// What the station needs to know, resolved from the mission.
pub struct StationSetup {
    /// The mission's name.
    pub mission: String,
    /// Its node name (the mission node hosting it; with several vehicles, `NODE-VEHICLE`).
    pub node: String,
    /// Its service name (`station`; with several vehicles, `station-VEHICLE`).
    pub service: String,
    /// The vehicle it follows, named in its lines, bar and summary when the mission has
    /// several (the FPMa's namespace, e.g. `rover2`); `None` in a one-vehicle mission.
    pub vehicle: Option<String>,
    /// The supervisor label of that vehicle's VAS (`air2/vas`), so only its restarts count.
    pub vas_label: Option<String>,
    /// Its namespace.
    pub namespace: Option<String>,
    /// A network.xml to join with; default Ethernet on loopback.
    pub network: Option<PathBuf>,
    /// The mission's discovery domain.
    pub domain: String,
    /// The plan file to upload.
    pub plan_file: PathBuf,
    /// The plan's name (from the file).
    pub plan_name: String,
    /// Prefix of the FPMa, e.g. `rover1/fpma`.
    pub fpma: String,
    /// Prefix of the VAS, e.g. `rover1/vas`.
    pub vas: String,
    /// The plan's waypoints flown with no in-flight change: (leg, lat, lon).
    pub nominal: Vec<(String, f64, f64)>,
    /// Its nominal length, metres.
    pub nominal_m: f64,
    /// A plan the FPMa must refuse, offered first (`<station refusedPlan>`).
    pub refused_plan: Option<PathBuf>,
    /// The run's flight log, where the station's commands and their answers go.
    pub log: Option<Arc<super::flightlog::FlightLog>>,
    /// Who presses Start (`<station start>`).
    pub start: StartBy,
    /// The plan's altitudes, take-off and landing, when an aircraft flies it.
    pub aircraft: Option<AircraftPlan>,
    /// What looks wrong in the plan without making it unflyable (a waypoint far from home),
    /// said before the upload.
    pub warnings: Vec<String>,
}

/// One waypoint the FPMa reported reached.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Reached {
    /// Sequence number in the FPMa's stream.
    pub seq: u64,
    /// Its leg.
    pub leg: String,
    /// Where, as the VAS reported it (or from the plan when that report was lost).
    pub lat: f64,
    /// Longitude.
    pub lon: f64,
}

/// The flight, summed up.
#[derive(Clone, Debug, serde::Serialize)]
pub struct Summary {
    /// The vehicle, in a mission of several.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub vehicle: Option<String>,
    /// Plan name.
    pub plan: String,
    /// Whether the FPMa said the plan was completed.
    pub completed: bool,
    /// Waypoints reached, in report order.
    pub reached: Vec<Reached>,
    /// Waypoints of the plan flown as planned.
    pub planned: usize,
    /// The reached waypoints are the plan's, each once, in order.
    pub in_order: bool,
    /// Metres flown, per the FPMa.
    pub flown_m: f64,
    /// Metres planned.
    pub planned_m: f64,
    /// From the plan's upload to its completion (or now), seconds.
    pub elapsed_s: f64,
    /// Times the VAS was restarted and the queue re-sent.
    pub vas_recoveries: u32,
    /// The failsafes that fired, in order.
    pub failsafes: Vec<FailsafeNote>,
    /// An aircraft's altitudes and landing against the plan's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub aircraft: Option<AircraftSummary>,
}

impl Summary {
    /// The human-readable form.
    pub fn text(&self, mission: &str) -> String {
        let who = match &self.vehicle {
            Some(v) => format!("mission {mission}, vehicle {v}"),
            None => format!("mission {mission}"),
        };
        let mut s = format!(
            "{who}: plan `{}` {} in {:.1} s\n",
            self.plan,
            if self.completed {
                "completed"
            } else {
                "NOT completed"
            },
            self.elapsed_s
        );
        s += &format!(
            "  waypoints: {} of {} planned reached{}\n",
            self.reached.len(),
            self.planned,
            if self.in_order {
                ", each once, in order"
            } else if self.as_planned() {
                " (the route an emergency rule chose)"
            } else {
                " (not the plan's sequence)"
            }
        );
        s += &format!(
            "  distance: {:.1} m flown of {:.1} m planned\n",
            self.flown_m, self.planned_m
        );
        if self.vas_recoveries > 0 {
            s += &format!(
                "  the VAS was restarted {} time(s); the FPMa re-sent its queue each time\n",
                self.vas_recoveries
            );
        }
        s += &failsafe::summary_text(&self.failsafes);
        if let Some(a) = &self.aircraft {
            s += &a.text();
        }
        s += "  reached:";
        for (i, r) in self.reached.iter().enumerate() {
            if i % 4 == 0 {
                s += "\n   ";
            }
            s += &format!(" #{} {} ({:.6},{:.6})", r.seq, r.leg, r.lat, r.lon);
        }
        s
    }
}

impl Summary {
    /// Flown as planned: the plan's waypoints in order, or another route an emergency rule
    /// chose by design (a battery rule sending the vehicle to the approach).
    pub fn as_planned(&self) -> bool {
        self.in_order || self.failsafes.iter().any(FailsafeNote::changes_route)
    }
}

/// How the station ended.
pub enum Outcome {
    /// The plan completed (with `--until-complete`, the station returns then).
    Completed(Summary),
    /// Asked to stop; the flight so far.
    Stopped(Summary),
    /// Something prevents the plan from being flown.
    Failed(String),
}

/// Runs the station until the plan completes (`until_complete`) or `stop`.
pub async fn run(
    setup: StationSetup,
    ui: Arc<Ui>,
    notices: broadcast::Receiver<Notice>,
    stop: CancellationToken,
    until_complete: bool,
) -> Outcome {
    let node = match open(&setup).await {
        Ok(n) => n,
        Err(e) => return Outcome::Failed(format!("station: {e:#}")),
    };
    let out = match follow(&node, &setup, &ui, notices, &stop, until_complete).await {
        Ok(o) => o,
        Err(e) => Outcome::Failed(format!("station: {e:#}")),
    };
    node.shutdown().await;
    out
}

async fn open(s: &StationSetup) -> anyhow::Result<Node> {
    let mut cfg = NetworkConfig::for_service(
        s.network.as_deref(),
        &s.node,
        Some(&s.domain),
        s.namespace.as_deref(),
    )
    .context("loading the network configuration")?;
    cfg.node.clone_from(&s.node);
    Node::open(&cfg).await.context("joining the network")
}

/// The plan's upload in flight.
type Upload = std::pin::Pin<
    Box<dyn std::future::Future<Output = Result<marea::FileReport, marea::FileSendError>> + Send>,
>;

fn upload(svc: &marea::Service, s: &StationSetup, sink: &str) -> Upload {
    let transfer = svc.send_file(
        &s.plan_file,
        sink,
        SendFileOptions {
            retry_for: SEND_RETRY,
            ..SendFileOptions::default()
        },
    );
    Box::pin(transfer.wait())
}

/// What the station knows of the flight.
struct Tracker<'a> {
    setup: &'a StationSetup,
    progress: Option<Progress>,
    state: Option<FlightState>,
    speed: f32,
    leg: Option<String>,
    reached: Vec<(u64, String)>,
    vas_points: BTreeMap<u64, (f64, f64)>,
    started: Option<Instant>,
    ended: Option<Instant>,
    recoveries: u32,
    /// The failsafes that fired.
    failsafes: Vec<FailsafeNote>,
    /// The FPMa's PlanCompleted event arrived (reliable, unlike the progress variable's last
    /// value, which a lossy radio may drop).
    completed_event: bool,
    /// The vehicle's last position.
    position: Option<Position>,
    /// What the VAS last said may be asked of it.
    allowed: Option<AllowedChanges>,
    /// An aircraft's flight, as it goes.
    flight: FlightRecord,
}

impl Tracker<'_> {
    fn fraction(&self) -> f64 {
        self.progress.as_ref().map_or(0.0, |p| p.fraction)
    }

    fn distances(&self) -> (f64, f64) {
        self.progress
            .as_ref()
            .map_or((0.0, self.setup.nominal_m), |p| (p.flown_m, p.planned_m))
    }

    /// The FPMa's ETAs, `(plan, leg)`, seconds of vehicle time (simulated seconds under a
    /// speed-up).
    fn etas(&self) -> (Option<f64>, Option<f64>) {
        self.progress
            .as_ref()
            .map_or((None, None), |p| (p.eta_s, p.leg_eta_s))
    }

    /// `ETA m:ss (leg m:ss)`, or `ETA -` before the vehicle has moved.
    fn eta_text(&self) -> String {
        let (plan, leg) = self.etas();
        match plan {
            None => "ETA -".into(),
            Some(p) => format!(
                "ETA {} (leg {})",
                ui_mmss(p),
                leg.map_or_else(|| "-".into(), ui_mmss)
            ),
        }
    }

    fn elapsed(&self) -> Duration {
        match (self.started, self.ended) {
            (Some(s), Some(e)) => e - s,
            (Some(s), None) => s.elapsed(),
            _ => Duration::ZERO,
        }
    }

    fn state_name(&self) -> String {
        self.state.map_or_else(|| "-".into(), |s| s.to_string())
    }

    fn bar_line(&self) -> String {
        let (flown, planned) = self.distances();
        let t = self.elapsed().as_secs();
        if self.setup.vehicle.is_some() {
            // One of several vehicles on one line: the short form.
            return format!(
                "{} {:>3.0}% wp {}/{} {}",
                ui::bar(self.fraction(), 10),
                self.fraction() * 100.0,
                self.reached.len(),
                self.setup.nominal.len(),
                self.state_name(),
            );
        }
        format!(
            "{} {:>3.0}%  leg {}  wp {}/{}  {:.0}/{:.0} m  {}  {:.1} m/s  {}:{:02}  {}",
            ui::bar(self.fraction(), 24),
            self.fraction() * 100.0,
            self.leg.as_deref().unwrap_or("-"),
            self.reached.len(),
            self.setup.nominal.len(),
            flown,
            planned,
            self.state_name(),
            self.speed,
            t / 60,
            t % 60,
            self.eta_text()
        )
    }

    fn summary(&self) -> Summary {
        let nominal = &self.setup.nominal;
        let legs_match = self.reached.len() == nominal.len()
            && self
                .reached
                .iter()
                .zip(nominal)
                .all(|((_, leg), (nleg, _, _))| leg == nleg);
        let increasing = self.reached.windows(2).all(|w| w[0].0 < w[1].0);
        let reached = self
            .reached
            .iter()
            .enumerate()
            .map(|(i, (seq, leg))| {
                let (lat, lon) = self.vas_points.get(seq).copied().unwrap_or_else(|| {
                    nominal
                        .get(i)
                        .filter(|n| &n.0 == leg)
                        .map_or((f64::NAN, f64::NAN), |n| (n.1, n.2))
                });
                Reached {
                    seq: *seq,
                    leg: leg.clone(),
                    lat,
                    lon,
                }
            })
            .collect();
        let (flown_m, planned_m) = self.distances();
        Summary {
            vehicle: self.setup.vehicle.clone(),
            plan: self.setup.plan_name.clone(),
            completed: self.completed_event || self.progress.as_ref().is_some_and(|p| p.completed),
            reached,
            planned: nominal.len(),
            in_order: legs_match && increasing,
            flown_m,
            planned_m,
            elapsed_s: self.elapsed().as_secs_f64(),
            vas_recoveries: self.recoveries,
            failsafes: self.failsafes.clone(),
            aircraft: self.setup.aircraft.as_ref().map(|a| self.flight.summary(a)),
        }
    }
}

/// The VAS's refusals of the operator's Start, asked again with a growing delay.
#[derive(Default)]
struct Refusals {
    count: u32,
    last: Option<String>,
}

impl Refusals {
    /// A refusal: how long to wait before asking again (1 s, doubling up to 8 s), and whether
    /// it repeats the last one (said once).
    fn next(&mut self, reason: &str) -> (Duration, bool) {
        let repeated = self.last.as_deref() == Some(reason);
        self.last = Some(reason.to_owned());
        let delay = Duration::from_secs(1 << self.count.min(3)).saturating_sub(KICK_AFTER);
        self.count += 1;
        (delay, repeated)
    }
}

/// Where the station is in bringing a restarted VAS back into the plan.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Recovery {
    /// Nothing to do.
    Idle,
    /// The VAS went away or restarted: wait for the new one to finish configuring.
    Waiting,
    /// The new VAS is configured: have the FPMa re-send its queue.
    Due,
}

async fn follow(
    node: &Node,
    s: &StationSetup,
    ui: &Ui,
    mut notices: broadcast::Receiver<Notice>,
    stop: &CancellationToken,
    until_complete: bool,
) -> anyhow::Result<Outcome> {
    let svc = node.service(&s.service)?;
    let (fpma_at, vas_at) = (s.fpma.as_str(), s.vas.as_str());
    let progress = fpma::PROGRESS.subscribe(&svc, fpma_at)?;
    let events = fpma::PLAN_EVENT.subscribe(&svc, fpma_at)?;
    let rejected = fpma::PLAN_REJECTED.subscribe(&svc, fpma_at)?;
    let state = vas::FLIGHT_STATE.subscribe(&svc, vas_at)?;
    let changes = vas::STATE_CHANGED.subscribe(&svc, vas_at)?;
    let vas_reached = vas::WAYPOINT_REACHED.subscribe(&svc, vas_at)?;
    let position = vas::POSITION.subscribe(&svc, vas_at)?;
    let allowed = vas::ALLOWED_CHANGES.subscribe(&svc, vas_at)?;
    let failsafes = vas::FAILSAFE.subscribe(&svc, vas_at)?;
    failsafe::start_heartbeat(&svc, &s.service)?;
    let opened = Instant::now();
    let pause = fpma::PAUSE.function(&svc, fpma_at)?;
    let resume = fpma::RESUME.function(&svc, fpma_at)?;
    let last_progress = fpma::LAST_PROGRESS.function(&svc, fpma_at)?;
    let mut asked_progress = false;

    // A file sink: no typed handle, its name written here.
    let sink = format!("{fpma_at}/plans");
    for w in &s.warnings {
        note(
            ui,
            s,
            &format!("station: WARNING: {w}"),
            json!({"event": "plan_warning", "text": w}),
        );
    }
    note(
        ui,
        s,
        &format!(
            "station: uploading {} to {sink} ({} waypoints, {:.0} m planned)",
            s.plan_file.display(),
            s.nominal.len(),
            s.nominal_m
        ),
        json!({"event": "uploading", "plan": s.plan_name, "to": sink, "waypoints": s.nominal.len(), "planned_m": s.nominal_m}),
    );
    match s.start {
        StartBy::Auto => note(
            ui,
            s,
            "station: usal run presses Start once the plan is loaded (start=\"auto\"; start=\"operator\" leaves it to the pilot)",
            json!({"event": "start_by", "by": "auto"}),
        ),
        StartBy::Operator => note(
            ui,
            s,
            &format!(
                "station: the pilot presses Start (start=\"operator\"): the FPMo's Start, or usal call {} '{{\"to\":\"WAYPOINT_NAVIGATION\"}}' --domain {}",
                vas::CHANGE_STATE.at(vas_at),
                s.domain
            ),
            json!({"event": "start_by", "by": "operator"}),
        ),
    }
    // The plan goes once the VAS has configured its autopilot, so the FPMa's request for
    // WAYPOINT_NAVIGATION cannot come too early and be refused (or after UPLOAD_ANYWAY).
    let mut send: Option<Upload> = None;
    let upload_anyway = tokio::time::sleep(UPLOAD_ANYWAY);
    tokio::pin!(upload_anyway);
    let mut kick_at: Option<Instant> = None;
    let vas_state_fn = vas::CHANGE_STATE.function(&svc, vas_at)?;
    let mut sent = false;
    let mut t = Tracker {
        setup: s,
        progress: None,
        state: None,
        speed: 0.0,
        leg: None,
        reached: Vec::new(),
        vas_points: BTreeMap::new(),
        started: None,
        ended: None,
        recoveries: 0,
        failsafes: Vec::new(),
        completed_event: false,
        position: None,
        allowed: None,
        flight: FlightRecord::default(),
    };
    let mut navigated = false;
    let mut refusals = Refusals::default();
    let mut recovery = Recovery::Idle;
    // The supervisor said the VAS restarted (the old one is gone: what the state stream says
    // from now on is the new one's).
    let mut restart_noticed = false;
    let mut last_attempt: Option<Instant> = None;
    let mut saw_configure = false;
    let mut completing: Option<Instant> = None;
    let mut reported = false;
    let mut notices_open = true;
    let mut unshown: std::collections::VecDeque<(u64, String, usize, Instant)> =
        std::collections::VecDeque::new();
    let mut tick = tokio::time::interval(Duration::from_millis(500));
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);

    loop {
        let mut line: Option<String> = None;
        let mut record: Option<serde_json::Value> = None;
        tokio::select! {
            () = stop.cancelled() => {
                ui.clear_bar();
                return Ok(Outcome::Stopped(t.summary()));
            }
            () = &mut upload_anyway, if send.is_none() => {
                note(ui, s,
                    &format!("station: the VAS is not configured after {UPLOAD_ANYWAY:?}; uploading the plan anyway"),
                    json!({"event": "note", "text": "uploading before the VAS is configured"}),
                );
                if let Err(e) = rehearse(&svc, s, ui, &mut t, opened).await {
                    return Ok(Outcome::Failed(e));
                }
                send = Some(upload(&svc, s, &sink));
            }
            r = async { send.as_mut().expect("guarded by the precondition").await }, if send.is_some() && !sent => {
                sent = true;
                command(s, &sink, json!({"file": s.plan_file.display().to_string()}),
                    r.as_ref().map(|rep| json!({"bytes": rep.size, "receiver": rep.receiver})).map_err(ToString::to_string));
                match r {
                    Ok(rep) => {
                        t.started = Some(Instant::now());
                        note(ui, s,
                            &format!("station: plan sent ({} bytes) to {}", rep.size, rep.receiver),
                            json!({"event": "plan_sent", "bytes": rep.size, "receiver": rep.receiver}),
                        );
                    }
                    Err(e) => return Ok(Outcome::Failed(format!("uploading the plan to {sink}: {e}"))),
                }
            }
            p = progress.recv() => {
                let p = p.context("following the plan's progress")?.value;
                if p.version > 0 {
                    if p.completed && completing.is_none() {
                        completing = Some(Instant::now());
                    }
                    t.leg.clone_from(&p.leg);
                    t.progress = Some(p);
                }
            }
            e = events.recv() => {
                let e = e.context("following the plan's events")?.value;
                match e.kind {
                    PlanEventKind::PlanLoaded { name } => {
                        line = Some(format!("plan `{name}` loaded (version {})", e.version));
                        record = Some(json!({"event": "plan_loaded", "name": name, "version": e.version}));
                    }
                    PlanEventKind::LegStarted { leg } => {
                        t.leg = Some(leg.clone());
                        line = Some(format!("leg {leg} started"));
                        record = Some(json!({"event": "leg_started", "leg": leg}));
                    }
                    PlanEventKind::WaypointReached { seq, leg } => {
                        t.reached.push((seq, leg.clone()));
                        if let Some(a) = &s.aircraft {
                            t.flight.reached(a, &leg, t.position.as_ref());
                        }
                        // Shown once the progress variable has caught up with it (it travels
                        // apart from events), so the line carries the distance at that point.
                        unshown.push_back((seq, leg, t.reached.len(), Instant::now()));
                    }
                    PlanEventKind::PlanCompleted => {
                        t.completed_event = true;
                        completing.get_or_insert_with(Instant::now);
                    }
                    k @ PlanEventKind::StageChanged { .. } => line = Some(k.to_string()),
                    PlanEventKind::LegCompleted { leg, skipped } => {
                        line = Some(format!("leg {leg} {}", if skipped { "skipped" } else { "completed" }));
                    }
                    PlanEventKind::IterationDone { leg, n } => {
                        line = Some(format!("loop {leg}: pass {n} done"));
                    }
                    PlanEventKind::EmergencyFired { rule } => {
                        let n = FailsafeNote::from_rule(&rule, opened.elapsed().as_secs_f64());
                        line = Some(n.line());
                        record = Some(json!({"event": "failsafe", "failsafe": n}));
                        t.failsafes.push(n);
                    }
                    PlanEventKind::TakenOver { by, items } => {
                        line = Some(format!("TAKEN OVER: the vehicle flies another ground station's mission ({by}, {items} items); the plan is paused until the operator resumes it (usal call <fpma>/resume), then Start"));
                        record = Some(json!({"event": "taken_over", "by": by, "items": items}));
                    }
                    other => line = Some(format!("plan: {other}")),
                }
            }
            r = rejected.recv() => {
                let r = r.context("following plan rejections")?.value;
                // Only the refusal of this station's own plan ends its run; a bad plan another
                // station or tool sent changes nothing the FPMa flies, and the flight goes on.
                let own_file = s.plan_file.file_name().and_then(|n| n.to_str());
                if r.from == node.name() && own_file == Some(r.file.as_str()) {
                    return Ok(Outcome::Failed(format!("the FPMa rejected the plan: {}", r.reason)));
                }
                line = Some(format!(
                    "the FPMa refused a plan {} sent ({}): {}; the flight goes on",
                    r.from, r.file, r.reason
                ));
                record = Some(json!({"event": "plan_refused", "from": r.from, "file": r.file, "reason": r.reason}));
            }
            st = state.recv() => {
                let st = st.context("following the VAS state")?.value;
                if t.state != Some(st) {
                    line = Some(format!("vehicle state {st}"));
                    record = Some(json!({"event": "state", "state": st.to_string()}));
                }
                t.state = Some(st);
                t.flight.state(st, t.position.as_ref());
                if send.is_none() && st != FlightState::ConfigureCheck {
                    if let Err(e) = rehearse(&svc, s, ui, &mut t, opened).await {
                        return Ok(Outcome::Failed(e));
                    }
                    send = Some(upload(&svc, s, &sink));
                }
                if st == FlightState::WaypointNavigation && t.started.is_some() {
                    navigated = true;
                }
                let done = t.progress.as_ref().is_some_and(|p| p.completed);
                if st == FlightState::ConfigureCheck {
                    saw_configure = true;
                    if navigated && !done && recovery == Recovery::Idle {
                        recovery = Recovery::Waiting;
                    }
                } else if recovery == Recovery::Waiting && (saw_configure || restart_noticed) {
                    // After the supervisor said the VAS restarted, any state but
                    // CONFIGURE_CHECK is the new one's, configured: its start (and that first
                    // change) may pass before this station's subscription reaches it, the
                    // identity handshake coming first.
                    recovery = Recovery::Due;
                }
            }
            c = changes.recv() => {
                let c = c.context("following the VAS state changes")?.value;
                if c.from == FlightState::ConfigureCheck && recovery == Recovery::Waiting {
                    recovery = Recovery::Due;
                }
            }
            f = failsafes.recv() => {
                let f = f.context("following the VAS's failsafes")?.value;
                let n = FailsafeNote::from_event(&f, opened.elapsed().as_secs_f64());
                line = Some(n.line());
                record = Some(json!({"event": "failsafe", "failsafe": n}));
                t.failsafes.push(n);
            }
            w = vas_reached.recv() => {
                let w = w.context("following the VAS's waypoints")?.value;
                t.vas_points.insert(w.seq, (w.lat, w.lon));
            }
            p = position.recv() => {
                let p = p.context("following the position")?.value;
                t.speed = p.speed;
                if let Some(a) = &s.aircraft {
                    t.flight.position(a, &p);
                }
                t.position = Some(p);
            }
            a = allowed.recv() => {
                t.allowed = Some(a.context("following what the VAS allows")?.value);
            }
            n = notices.recv(), if notices_open => match n {
                Ok(Notice::Restarted { kind: "vas", label, pid })
                    if s.vas_label.as_deref().is_none_or(|l| l == label) =>
                {
                    line = Some(format!("{label} restarted (pid {pid}): waiting for it to configure"));
                    if navigated && recovery == Recovery::Idle {
                        recovery = Recovery::Waiting;
                        saw_configure = false;
                        restart_noticed = true;
                    }
                }
                Ok(_) | Err(broadcast::error::RecvError::Lagged(_)) => {}
                Err(broadcast::error::RecvError::Closed) => notices_open = false,
            },
            _ = tick.tick() => {}
        }

        // The operator's Start: once the plan is loaded and the VAS parks with waypoints
        // queued, ask for WAYPOINT_NAVIGATION (the FPMa never does: the flight state is the
        // operator's); an aircraft takes off first and navigates once it has climbed.
        let request = t.state.and_then(|st| {
            let climbed = match (&s.aircraft, &t.position) {
                (Some(a), Some(p)) => a.climbed(p),
                (Some(_), None) => false,
                (None, _) => true,
            };
            aircraft::start_request(st, t.allowed.as_ref(), climbed)
        });
        let waiting = s.start == StartBy::Auto
            && t.started.is_some()
            && !navigated
            && request.is_some()
            && t.progress.as_ref().is_some_and(|p| !p.completed);
        match (waiting, kick_at, request) {
            (true, None, _) => kick_at = Some(Instant::now()),
            (true, Some(at), Some(to)) if at.elapsed() >= KICK_AFTER => {
                kick_at = Some(Instant::now() + Duration::from_secs(3600));
                let answer = vas_state_fn
                    .call(&StateChangeRequest { to }, CALL_TIMEOUT)
                    .await;
                command(
                    s,
                    &vas::CHANGE_STATE.at(vas_at),
                    json!({"to": to.to_string()}),
                    answer
                        .as_ref()
                        .map(|a| serde_json::to_value(a).unwrap_or_default())
                        .map_err(ToString::to_string),
                );
                match answer {
                    Ok(_) => {
                        refusals = Refusals::default();
                        let takeoff_alt = s
                            .aircraft
                            .as_ref()
                            .and_then(|a| a.takeoff_alt.map(|t| (t, a.alt_ref)));
                        match (to, takeoff_alt) {
                            (FlightState::TakeOff, Some((alt, r))) => note(ui, s,
                                &format!("station: plan ready and the aircraft parked; taking off (TAKE_OFF) to {alt:.0} m {r}, as the operator"),
                                json!({"event": "takeoff_kicked", "alt": alt, "alt_ref": r.to_string()}),
                            ),
                            (FlightState::TakeOff, None) => note(ui, s,
                                "station: plan ready and the aircraft parked; taking off (TAKE_OFF), as the operator",
                                json!({"event": "takeoff_kicked"}),
                            ),
                            _ if t.state == Some(FlightState::TakeOff) => note(ui, s,
                                &format!("station: climbed to {:.1} m; started the plan (WAYPOINT_NAVIGATION), as the operator",
                                    t.position.as_ref().map_or(f64::NAN, |p| s.aircraft.as_ref().map_or(p.alt_rel, |a| a.altitude(p)))),
                                json!({"event": "navigation_kicked"}),
                            ),
                            _ => note(ui, s,
                                "station: plan ready and the vehicle parked; started it (WAYPOINT_NAVIGATION), as the operator",
                                json!({"event": "navigation_kicked"}),
                            ),
                        }
                    }
                    Err(e) => {
                        // Asked again a little later (the queue may still be on its way),
                        // less and less often; the same refusal is said once.
                        let (delay, repeated) = refusals.next(&e.to_string());
                        kick_at = Some(Instant::now() + delay);
                        if !repeated {
                            note(ui, s,
                                &format!("station: the vehicle stays {} and the VAS refused {to}: {e} (asked again until it accepts)", t.state_name()),
                                json!({"event": "navigation_refused", "to": to.to_string(), "reason": e.to_string()}),
                            );
                        }
                    }
                }
            }
            (false, _, _) => kick_at = None,
            _ => {}
        }

        if recovery == Recovery::Due && s.start == StartBy::Operator {
            // The pilot brings the vehicle back into the plan (the FPMo's Resume, then Start).
            recovery = Recovery::Idle;
            restart_noticed = false;
            navigated = false;
            note(
                ui,
                s,
                "station: the VAS is back, parked: resuming the plan is the pilot's (start=\"operator\")",
                json!({"event": "recovery_left_to_operator"}),
            );
        }
        if recovery == Recovery::Due && last_attempt.is_none_or(|t| t.elapsed() >= RETRY) {
            last_attempt = Some(Instant::now());
            // The new VAS has an empty queue and the FPMa does not know it: a pause empties the
            // FPMa's look-ahead at the VAS and a resume refills it and restarts navigation, from
            // the first waypoint the FPMa has not seen reached.
            // The FPMa may itself be rediscovered after the disturbance.
            pause.wait_provider(CALL_TIMEOUT).await;
            let answer = pause.call(&(), CALL_TIMEOUT).await;
            command(
                s,
                &fpma::PAUSE.at(fpma_at),
                json!(null),
                answer
                    .as_ref()
                    .map(|a| serde_json::to_value(a).unwrap_or_default())
                    .map_err(ToString::to_string),
            );
            let paused = match answer {
                Ok(_) => Ok(()),
                Err(e) if e.to_string().contains("already paused") => Ok(()),
                Err(e) => Err(e),
            };
            let resumed = match paused {
                Ok(()) => {
                    let answer = resume.call(&(), CALL_TIMEOUT).await;
                    command(
                        s,
                        &fpma::RESUME.at(fpma_at),
                        json!(null),
                        answer
                            .as_ref()
                            .map(|a| serde_json::to_value(a).unwrap_or_default())
                            .map_err(ToString::to_string),
                    );
                    answer.map(|_| ())
                }
                Err(e) => Err(e),
            };
            match resumed {
                Ok(()) => {
                    recovery = Recovery::Idle;
                    restart_noticed = false;
                    last_attempt = None;
                    // The new VAS parks with the queue refilled: the operator (this station)
                    // starts it again, as after the upload.
                    navigated = false;
                    t.recoveries += 1;
                    note(
                        ui,
                        s,
                        "station: the VAS came back; the FPMa re-sent its queue (pause, resume)",
                        json!({"event": "vas_recovered"}),
                    );
                }
                // Tried again on the next input or tick.
                Err(e) => note(
                    ui,
                    s,
                    &format!("station: re-sending the queue to the restarted VAS failed: {e}"),
                    json!({"event": "vas_recovery_failed", "reason": e.to_string()}),
                ),
            }
        }

        let mut out: Vec<(String, Option<serde_json::Value>)> =
            line.map(|l| (l, record)).into_iter().collect();
        let caught_up = t.progress.as_ref().and_then(|p| p.last_reached);
        let flush_all = completing.is_some();
        while let Some((seq, leg, n, at)) = unshown.front().cloned() {
            if !(flush_all
                || caught_up.is_some_and(|r| r >= seq)
                || at.elapsed() >= Duration::from_millis(400))
            {
                break;
            }
            unshown.pop_front();
            let (flown, planned) = t.distances();
            let (eta_s, leg_eta_s) = t.etas();
            out.push((
                format!(
                    "waypoint {n}/{} reached (#{seq}, leg {leg}); {flown:.0} of {planned:.0} m flown; {}; {}",
                    s.nominal.len(),
                    t.state_name(),
                    t.eta_text()
                ),
                Some(json!({"event": "waypoint", "n": n, "of": s.nominal.len(), "seq": seq,
                    "leg": leg, "flown_m": flown, "planned_m": planned, "state": t.state_name(),
                    "eta_s": eta_s, "leg_eta_s": leg_eta_s})),
            ));
        }
        if out.is_empty() && !reported {
            ui.progress_of(s.vehicle.as_deref(), &t.bar_line(), None, None);
        }
        for (l, record) in out {
            if reported {
                note(
                    ui,
                    s,
                    &l,
                    record.unwrap_or_else(|| json!({"event": "note", "text": l})),
                );
            } else {
                ui.progress_of(s.vehicle.as_deref(), &t.bar_line(), Some(&l), record);
            }
        }
        // Settled when both the progress variable and the event say so and every waypoint
        // was seen, or a moment after the variable said so. Over a lossy radio the variable's
        // last value may be lost (it is best effort; the FPMa repeats it every 2 s), the event
        // is not: on the event alone, wait long enough for a repeat to bring the final
        // distance, then settle anyway.
        // An aircraft whose plan lands is done once it is parked on the ground, disarmed (or
        // a while after, to say it is not).
        let on_ground = s
            .aircraft
            .as_ref()
            .is_none_or(|a| a.landing.is_none() || t.flight.parked_after_flight());
        // Completed by the event alone and no repeat of the variable yet: ask the FPMa for
        // its last progress (a call, which a lossy radio does not lose), once.
        if let Some(since) = completing {
            let progress_done = t.progress.as_ref().is_some_and(|p| p.completed);
            if t.completed_event && !progress_done && !asked_progress && since.elapsed() >= SETTLE {
                asked_progress = true;
                let ask = last_progress.call(&(), SETTLE);
                if let Ok(Ok(p)) = tokio::time::timeout(2 * SETTLE, ask).await {
                    if p.version > 0 {
                        t.progress = Some(p);
                    }
                }
            }
        }
        let settled = completing.is_some_and(|since| {
            let progress_done = t.progress.as_ref().is_some_and(|p| p.completed);
            let waited = since.elapsed() >= SETTLE_ON_EVENT;
            (on_ground || waited)
                && ((progress_done && t.completed_event && t.reached.len() >= s.nominal.len())
                    || (progress_done && since.elapsed() >= SETTLE)
                    || (t.completed_event && waited))
        });
        if settled && !reported {
            reported = true;
            t.ended = Some(Instant::now());
            ui.clear_bar();
            let summary = t.summary();
            if until_complete {
                return Ok(Outcome::Completed(summary));
            }
            note(
                ui,
                s,
                &summary.text(&s.mission),
                json!({"event": "summary", "summary": summary}),
            );
            note(
                ui,
                s,
                "plan completed; the services keep running (Ctrl-C stops them)",
                json!({"event": "completed"}),
            );
        }
    }
}

/// Seconds as `m:ss` (whole seconds, rounded).
/// Offers the mission's `refusedPlan`, if any, before the plan itself.
async fn rehearse(
    svc: &marea::Service,
    s: &StationSetup,
    ui: &Ui,
    t: &mut Tracker<'_>,
    opened: Instant,
) -> Result<(), String> {
    let Some(path) = &s.refused_plan else {
        return Ok(());
    };
    let at = opened.elapsed().as_secs_f64();
    let n = failsafe::rehearse_refusal(
        svc,
        &s.fpma,
        path,
        at,
        SEND_RETRY.min(Duration::from_secs(20)),
    )
    .await
    .map_err(|e| format!("station: {e}"))?;
    note(
        ui,
        s,
        &n.line(),
        json!({"event": "failsafe", "failsafe": n}),
    );
    t.failsafes.push(n);
    Ok(())
}

fn ui_mmss(s: f64) -> String {
    let s = if s.is_finite() {
        s.max(0.0).round() as u64
    } else {
        0
    };
    format!("{}:{:02}", s / 60, s % 60)
}

/// A note of this station: named after its vehicle in a mission of several.
fn note(ui: &Ui, s: &StationSetup, text: &str, mut record: serde_json::Value) {
    match &s.vehicle {
        None => ui.note(text, record),
        Some(v) => {
            if let Some(o) = record.as_object_mut() {
                o.insert("vehicle".into(), v.clone().into());
            }
            ui.note(&format!("{v}: {text}"), record);
        }
    }
}

/// Records one of the station's commands and its answer in the flight log.
fn command(
    s: &StationSetup,
    name: &str,
    args: serde_json::Value,
    answer: Result<serde_json::Value, String>,
) {
    let Some(log) = &s.log else { return };
    let mut r = json!({"name": name, "args": args});
    match answer {
        Ok(a) => r["answer"] = a,
        Err(e) => r["error"] = e.into(),
    }
    log.record("command", r);
}
