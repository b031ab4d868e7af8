//! The MAVLink layer's driver task: owns the [`RollingQueue`], applies the VAL's commands
//! and the manager's events in order, performs the queue's actions on the autopilot (retrying
//! on a tick) and infers waypoint progress when the autopilot does not report it.

use super::progress::{backtracks_judged, metres, PassWatch, WallSpeed};
use super::*;

/// Reads the parameters and sets the telemetry rates (`AP_Parameters`).
pub(super) async fn configure(
    mgr: &Arc<MavlinkManager>,
    cfg: &MavlinkApConfig,
) -> Result<(), AutopilotError> {
    match mgr.params_list().await {
        Ok(p) => tracing::info!("autopilot has {} parameters", p.len()),
        Err(e) => tracing::warn!("reading parameters: {e}"),
    }
    let t = cfg.telemetry_hz;
    let s = cfg.status_hz;
    mgr.request_telemetry(&[
        (Telemetry::Position, t),
        (Telemetry::Attitude, t),
        (Telemetry::VfrHud, t),
        (Telemetry::SysStatus, s),
        (Telemetry::MissionCurrent, s),
    ])
    .await
    .map_err(|e| AutopilotError::NotConnected(e.to_string()))?;
    match mgr.request_capabilities().await {
        Ok(Some(c)) => tracing::info!("autopilot capabilities {c:#x}"),
        Ok(None) => tracing::info!("autopilot did not report its capabilities"),
        Err(e) => tracing::warn!("asking for AUTOPILOT_VERSION: {e}"),
    }
    probe_partial(mgr).await;
    request_home(mgr);
    Ok(())
}

/// Asks for the autopilot's home beside the caller (the answer is a [`MavEvent::Home`]); an
/// autopilot that does not tell is logged, not an error: the stations then draw no home.
pub(super) fn request_home(mgr: &Arc<MavlinkManager>) {
    let mgr = mgr.clone();
    tokio::spawn(async move {
        if let Err(e) = mgr.request_home().await {
            tracing::info!("asking for HOME_POSITION: {e}");
        }
    });
}

/// Finds out on the ground, once per connection, whether the autopilot has partial mission
/// writes (a short probe), so the rolling queue does not find out in flight.
pub(super) async fn probe_partial(mgr: &MavlinkManager) {
    tracing::info!("autopilot family: {}", mgr.family().name());
    if let Err(e) = mgr.probe_partial_writes().await {
        tracing::warn!("probing partial mission writes: {e}");
    }
}

/// Why a queue action failed.
enum ExecError {
    /// The autopilot has no partial mission writes: whole windows from now on.
    PartialUnsupported,
    /// The transfer failed.
    Mission(MissionError),
}

/// Why the rolling queue could not be laid out on the autopilot.
#[derive(Debug, thiserror::Error)]
pub(super) enum QueueError {
    /// A mission transfer failed.
    #[error("{0}")]
    Mission(MissionError),
    /// Actions kept coming without the autopilot ever holding what it should.
    #[error("the queue did not settle")]
    Unsettled,
}

impl QueueError {
    /// The autopilot refused a transfer (a MISSION_ACK result such as NO_SPACE or DENIED):
    /// unlike a lost frame, worth telling the ground.
    fn is_refusal(&self) -> bool {
        matches!(self, Self::Mission(MissionError::Rejected(_)))
    }
}

/// Performs one queue action on the autopilot, whose mission is laid out as `layout` says.
/// `item0` is what a whole upload puts in item 0 where item 0 is an ordinary item (not
/// ArduPilot's home): the target, so an autopilot that falls back to item 0 after the upload
/// keeps driving where it was going.
async fn exec(
    mgr: &MavlinkManager,
    home: Option<(f64, f64)>,
    item0: Option<&Waypoint>,
    layout: &Layout,
    action: &QueueAction<Waypoint>,
) -> Result<(), ExecError> {
    let other = ExecError::Mission;
    match action {
        QueueAction::Upload(items) => {
            let home = home
                .or_else(|| items.first().map(|w| (w.lat, w.lon)))
                .unwrap_or_default();
            let first = match item0 {
                Some(w) if !mgr.family().item0_is_home() => mission_item(w),
                _ => MissionItem::waypoint(home.0, home.1, 0.0),
            };
            let mut mission = vec![first];
            mission.extend(layout.items(items));
            tracing::debug!("queue: upload {} slots", items.len());
            mgr.mission_upload(&mission).await.map_err(other)
        }
        QueueAction::WritePartial { start, items } => {
            let (seq, mission) = layout.partial(*start, items);
            tracing::debug!("queue: write slot {start} (+{})", items.len() - 1);
            match mgr.mission_write_partial(seq, &mission).await {
                Ok(()) => Ok(()),
                Err(MissionError::PartialUnsupported) => {
                    tracing::warn!(
                        "partial mission writes unsupported on this autopilot: uploading whole windows"
                    );
                    Err(ExecError::PartialUnsupported)
                }
                Err(MissionError::RetriesExhausted {
                    stage: MissionStage::Start,
                    ..
                }) => {
                    tracing::warn!(
                        "partial mission writes unanswered: uploading whole windows from now on"
                    );
                    Err(ExecError::PartialUnsupported)
                }
                Err(e) => Err(ExecError::Mission(e)),
            }
        }
        QueueAction::SetCurrent(slot) => {
            let seq = layout.seq(*slot);
            tracing::debug!("queue: set current slot {slot} (item {seq})");
            mgr.mission_set_current(seq).await.map_err(other)
        }
    }
}

/// How long a set-current after a reach waits for the autopilot to report its own advance
/// (MISSION_CURRENT) before going ahead without it, when it reports no reaches (progress is
/// inferred from its position, and its advance may never be reported).
const ADVANCE_WAIT: std::time::Duration = std::time::Duration::from_millis(400);

/// The same wait for an autopilot that reports its reaches: it moves its current item on
/// after each, and may take long to (MAVSDK's mission server under load took over 400 ms); a
/// set-current sent before its advance would be overridden by it, sending the vehicle one
/// waypoint too far. Meanwhile the vehicle drives on to the next slot or holds: nothing is
/// lost by waiting.
const ADVANCE_WAIT_REPORTING: std::time::Duration = std::time::Duration::from_secs(3);

pub(super) struct Driver {
    mgr: Arc<MavlinkManager>,
    kind: VehicleKind,
    queue: RollingQueue<Waypoint>,
    events: broadcast::Sender<ApEvent>,
    /// The state the VAL last commanded (or the autopilot's own choice, once reported).
    commanded: Option<FlightState>,
    last_mode: Option<String>,
    /// The manager's [`VehicleState::restorations`] as of the last link restoration handled.
    restorations_seen: u32,
    last_reached: Option<u64>,
    home: Option<(f64, f64)>,
    /// The last queue action failed: wait for the tick before retrying.
    failing: bool,
    /// The manager's events.
    mav: broadcast::Receiver<MavEvent>,
    /// Events taken from `mav` while a queue action ran that need more than bookkeeping.
    deferred: VecDeque<MavEvent>,
    /// The speed last commanded with DO_CHANGE_SPEED (0: the autopilot's default).
    speed_sent: Option<f64>,
    /// The autopilot refused DO_CHANGE_SPEED or never answered it, since (re)connecting: it is
    /// not asked again (each unanswered try held the queue for the command's whole retry
    /// time, long enough for a fast vehicle to run off the end of its window).
    speed_unsupported: bool,
    /// The autopilot reported a waypoint reached since (re)connecting; until it does, progress
    /// is inferred from its position.
    reports_progress: bool,
    /// Latest position (lat, lon).
    position: Option<(f64, f64)>,
    /// Progress inferred from position, on the leg to the target.
    pass: PassWatch,
    /// The last waypoint and its slot, when the autopilot left AUTO on the way to it (most
    /// likely the mission ended there and its report is late, lost or never sent): a late
    /// report of that slot, or a position at or past it, still counts it.
    last_pending: Option<(u16, Waypoint)>,
    /// What the last whole upload put in item 0 where it is an ordinary item.
    item0: Option<Waypoint>,
    /// When the last waypoint was reached (a set-current waits for the autopilot's own
    /// advance after it, [`ADVANCE_WAIT`] or [`ADVANCE_WAIT_REPORTING`] at most).
    reached_at: Option<std::time::Instant>,
    /// Times the vehicle's reported current item went back to an item already passed while
    /// navigating (each is a drive back toward a passed waypoint).
    backtracks: u64,
    /// A whole upload is under way: the autopilot's reports of its current item may already
    /// name the mission being committed, not the one we know it holds.
    uploading: bool,
    /// Where the DO_LAND_START markers are on board (between the queue's slots).
    markers: Layout,
    /// The vehicle's speed in wall-clock time, and how long the last whole upload took: a
    /// marker comes or goes next to the target only if an upload ends before it gets there.
    wall_speed: WallSpeed,
    upload_took: Duration,
    /// An upload changed a marker before the slot the vehicle drives to (it got there while
    /// the upload ran): the autopilot's current item names another item until the restoring
    /// set-current, and its progress reports are not taken meanwhile ([`Self::index_stale`]).
    renumbered_target: bool,
    /// The last queue failure raised as an alarm (a refusal such as NO_SPACE or DENIED repeats
    /// on every retry; the ground hears it once until it changes or the queue recovers).
    queue_error: Option<String>,
    /// Home's altitude above mean sea level, from the last position (MSL minus relative).
    home_alt_msl: Option<f64>,
    /// Put a rebooted autopilot back in the commanded state (`resumeAfterReboot`).
    pub(super) resume_after_reboot: bool,
    /// The family-specific part the configuration fixed; `None`: the heartbeat's family.
    fixed_modes: Option<&'static dyn ApFamily>,
    /// The autopilot ended its mission at its last item on board with waypoints still queued
    /// (a wrap or a growing write came too late): navigation is restarted, and the mode it
    /// ends the mission in is not taken for a pilot's choice meanwhile.
    restart: bool,
    /// Until then, the autopilot seen out of AUTO after a restart is taken for the end of
    /// the mission heard late (its mode change may arrive after the restart on a lossy link,
    /// the restart then finding it "already" in AUTO), and navigation is restarted again.
    restart_guard_until: Option<std::time::Instant>,
    /// Restarts since a waypoint was last reached normally (at most [`MAX_RESTARTS`]).
    restarts_in_row: u8,
}

/// Restarts in a row after early mission ends (or failed restarts) before the VAS follows the
/// autopilot out of WAYPOINT_NAVIGATION.
const MAX_RESTARTS: u8 = 3;

impl Driver {
    pub(super) fn new(
        mgr: Arc<MavlinkManager>,
        kind: VehicleKind,
        queue: RollingQueue<Waypoint>,
        events: broadcast::Sender<ApEvent>,
        fixed_modes: Option<&'static dyn ApFamily>,
    ) -> Self {
        Self {
            mav: mgr.subscribe(),
            mgr,
            kind,
            queue,
            events,
            commanded: None,
            last_mode: None,
            restorations_seen: 0,
            last_reached: None,
            home: None,
            failing: false,
            deferred: VecDeque::new(),
            speed_sent: None,
            speed_unsupported: false,
            reports_progress: false,
            position: None,
            pass: PassWatch::default(),
            last_pending: None,
            item0: None,
            reached_at: None,
            backtracks: 0,
            uploading: false,
            markers: Layout::default(),
            wall_speed: WallSpeed::default(),
            upload_took: Duration::from_secs(1),
            renumbered_target: false,
            queue_error: None,
            home_alt_msl: None,
            resume_after_reboot: false,
            fixed_modes,
            restart: false,
            restart_guard_until: None,
            restarts_in_row: 0,
        }
    }

    /// Whether a mode out of AUTO is (probably) the autopilot ending its mission early, for
    /// which navigation is restarted: a restart is pending, or one was just made.
    fn early_end_mode(&mut self, mode: &str) -> bool {
        if mode == "AUTO" || self.commanded != Some(FlightState::WaypointNavigation) {
            return false;
        }
        // With the last waypoint alone left, the mission most likely ended there (its report
        // late): that end is followed as usual.
        let guarded = self.queue.len() >= 2
            && self
                .restart_guard_until
                .is_some_and(|t| std::time::Instant::now() < t);
        if !self.restart && guarded && self.restarts_in_row < MAX_RESTARTS {
            self.restart = true;
        }
        self.restart
    }

    /// The family-specific part in force: the configured one, else the heartbeat's.
    fn modes(&self) -> &'static dyn ApFamily {
        self.fixed_modes
            .unwrap_or_else(|| family_modes(self.mgr.family()))
    }

    pub(super) async fn run(mut self, mut cmds: mpsc::Receiver<Cmd>, cancel: CancellationToken) {
        let mut tick = interval(Duration::from_millis(250));
        loop {
            while let Some(ev) = self.deferred.pop_front() {
                self.on_mav(ev).await;
            }
            tokio::select! {
                _ = cancel.cancelled() => break,
                cmd = cmds.recv() => match cmd {
                    Some(cmd) => self.on_cmd(cmd).await,
                    None => break,
                },
                ev = self.mav.recv() => match ev {
                    Ok(ev) => {
                        if self.absorb(ev) {
                            self.pump().await;
                        }
                    }
                    Err(broadcast::error::RecvError::Lagged(n)) => {
                        tracing::warn!("APL lagged {n} MAVLink events; resynchronising");
                        self.restorations_handled();
                        self.resync().await;
                    }
                    Err(broadcast::error::RecvError::Closed) => break,
                },
                _ = tick.tick() => {
                    self.failing = false;
                    let wait = if self.reports_progress {
                        ADVANCE_WAIT_REPORTING
                    } else {
                        ADVANCE_WAIT
                    };
                    if self.queue.awaits_advance()
                        && self.reached_at.is_none_or(|t| t.elapsed() >= wait)
                    {
                        tracing::debug!("queue: the autopilot did not report its advance; going on");
                        self.queue.assume_advanced();
                    }
                    self.resync().await;
                }
            }
        }
    }

    fn emit(&self, e: ApEvent) {
        let _ = self.events.send(e);
    }

    fn alarm(&self, severity: Severity, text: impl Into<String>) {
        self.emit(ApEvent::Alarm(Alarm {
            severity,
            text: text.into(),
        }));
    }

    fn queue_status(&self) -> QueueStatus {
        QueueStatus {
            queued: self.queue.len() as u64,
            target: self.queue.target().map(|w| w.seq),
            last_reached: self.last_reached,
            replacing: self.queue.is_replacing(),
            backtracks: self.backtracks,
        }
    }

    async fn on_cmd(&mut self, cmd: Cmd) {
        match cmd {
            Cmd::ChangeState(to, reply) => {
                let r = self.change_state(to).await;
                let _ = reply.send(r);
            }
            Cmd::DirectTo([lat, lon, alt, speed], reply) => {
                let r = if self.commanded == Some(FlightState::Directed) {
                    self.modes()
                        .direct_to(&self.mgr, lat, lon, alt as f32, speed as f32)
                        .await
                        .map_err(|e| AutopilotError::Refused(e.to_string()))
                } else {
                    Err(AutopilotError::Refused(format!(
                        "a DIRECTED target needs DIRECTED, not {}",
                        self.commanded
                            .map_or_else(|| "CONFIGURE_CHECK".to_owned(), |s| s.to_string())
                    )))
                };
                let _ = reply.send(r);
            }
            Cmd::Push(wps, max_queued, reply) => {
                if let Err(e) = check_room(self.queue.len() as u64, wps.len(), max_queued) {
                    let _ = reply.send(Err(e));
                    return;
                }
                self.queue.push(wps);
                let _ = reply.send(Ok(self.queue_status()));
                if self.mission_ended_in_navigation() {
                    // An aircraft holds over its last waypoint in AUTO: the waypoints pushed
                    // since extend its navigation, as they would have before it got there.
                    tracing::info!("navigation resumed with the waypoints pushed since its end");
                    if let Err(e) = self.change_state(FlightState::WaypointNavigation).await {
                        self.alarm(
                            Severity::Warning,
                            format!("resuming navigation with the new waypoints: {e}"),
                        );
                    }
                    return;
                }
                self.pump().await;
            }
            Cmd::Clear(reply) => {
                self.queue.clear();
                let _ = reply.send(self.queue_status());
            }
            Cmd::Status(reply) => {
                let _ = reply.send(self.queue_status());
            }
            Cmd::Command(cmd, reply) => {
                let r = self.command(cmd).await;
                let _ = reply.send(r);
            }
        }
    }

    /// Navigation was commanded and the autopilot ended its mission at the last waypoint
    /// queued, still in AUTO (a copter or plane holding there), with waypoints queued since.
    fn mission_ended_in_navigation(&self) -> bool {
        let s = self.mgr.state();
        self.commanded == Some(FlightState::WaypointNavigation)
            && !self.queue.is_running()
            && !self.queue.is_empty()
            && !self.restart
            && s.link_up
            && s.mode_name.is_some()
            && self
                .modes()
                .mode_for(self.kind, FlightState::WaypointNavigation)
                .map(|(mode, _)| mode)
                == s.mode_name
    }

    /// ARM, DISARM, or DIRECTED flight (entering DIRECTED first): the VAL checked it.
    async fn command(&mut self, cmd: VehicleCommand) -> Result<(), AutopilotError> {
        let refused = |e: &dyn std::fmt::Display| AutopilotError::Refused(format!("{cmd}: {e}"));
        match cmd {
            VehicleCommand::Arm => self.mgr.arm(true).await.map_err(|e| refused(&e)),
            VehicleCommand::Disarm => self.mgr.arm(false).await.map_err(|e| refused(&e)),
            VehicleCommand::Directed(t) => {
                let Some((lat, lon)) = self.position else {
                    return Err(refused(&"no position from the autopilot yet"));
                };
                if self.commanded != Some(FlightState::Directed) {
                    self.change_state(FlightState::Directed).await?;
                }
                // The airspeed for a plane, the ground speed for a copter.
                let speed_kind = if self.kind == VehicleKind::Plane {
                    0.0
                } else {
                    1.0
                };
                let speed = [speed_kind, t.speed, -1.0, 0.0, 0.0, 0.0, 0.0];
                self.mgr
                    .command_long(MavCmd::MAV_CMD_DO_CHANGE_SPEED, speed)
                    .await
                    .map_err(|e| refused(&e))?;
                let (to_lat, to_lon) = directed_point((lat, lon), &t);
                // DO_REPOSITION in a COMMAND_LONG carries no frame: the altitude is MSL.
                let alt_msl = t.alt + self.home_alt_msl.unwrap_or(0.0);
                let reposition = [
                    t.speed,
                    0.0,
                    0.0,
                    f32::NAN,
                    to_lat as f32,
                    to_lon as f32,
                    alt_msl as f32,
                ];
                self.mgr
                    .command_long(MavCmd::MAV_CMD_DO_REPOSITION, reposition)
                    .await
                    .map_err(|e| refused(&e))?;
                tracing::info!(
                    "DIRECTED: bearing {}°, {} m/s, {} m above home",
                    t.bearing,
                    t.speed,
                    t.alt
                );
                Ok(())
            }
        }
    }

    async fn change_state(&mut self, to: FlightState) -> Result<(), AutopilotError> {
        let modes = self.modes();
        let Some((mode, arming)) = modes.mode_for(self.kind, to) else {
            return Err(AutopilotError::Unsupported(format!(
                "no autopilot mode for {to} on a {}",
                self.kind
            )));
        };
        let refused = |e: &dyn std::fmt::Display| AutopilotError::Refused(e.to_string());
        let previous = self.commanded.replace(to);
        if to == FlightState::WaypointNavigation {
            if self.queue.is_empty() {
                self.commanded = previous;
                return Err(AutopilotError::Refused("no waypoints queued".into()));
            }
            self.queue.stop();
            self.queue.start();
            if let Err(e) = self.prime().await {
                self.queue.stop();
                self.commanded = previous;
                return Err(AutopilotError::Refused(format!("priming the queue: {e}")));
            }
        } else if to == FlightState::Parking {
            // Parking after a landing: ArduPilot reports the landing item reached after the
            // disarm that made us park, and this may run before that report is read.
            self.stop_queue_keeping_last();
        } else {
            self.queue.stop();
        }
        if to == FlightState::TakeOff && self.kind == VehicleKind::Plane {
            // ArduPlane's TAKEOFF mode climbs to TKOFF_ALT (above home): the queue's take-off
            // altitude, so the climb ends where the plan's begins (with nothing queued, the
            // autopilot's own TKOFF_ALT).
            if let Some(alt) = self.takeoff_alt_above_home() {
                if let Err(e) = self.mgr.param_set("TKOFF_ALT", alt).await {
                    self.queue.stop();
                    self.commanded = previous;
                    return Err(AutopilotError::Refused(format!(
                        "setting the take-off altitude (TKOFF_ALT {alt} m): {e}"
                    )));
                }
            }
        }
        // A parked copter sits in LAND, where ArduCopter refuses to arm: a take-off enters
        // its mode (GUIDED) first and arms there; navigation arms before switching to AUTO.
        let arm_first = to != FlightState::TakeOff;
        if arm_first && arming == Arming::Arm && !self.mgr.state().armed {
            if let Err(e) = self.mgr.arm(true).await {
                self.commanded = previous;
                return Err(refused(&e));
            }
        }
        if to == FlightState::Landing && mode == "AUTO" {
            if let Err(e) = self.lay_out_landing().await {
                self.commanded = previous;
                return Err(AutopilotError::Refused(format!(
                    "laying out the landing: {e}"
                )));
            }
        }
        let first_slot = self.queue.current_slot().unwrap_or(1);
        if let Err(e) = modes.enter(&self.mgr, to, mode, first_slot).await {
            self.queue.stop();
            self.commanded = previous;
            return Err(refused(&e));
        }
        if !arm_first && arming == Arming::Arm && !self.mgr.state().armed {
            if let Err(e) = self.mgr.arm(true).await {
                // Back to where it was, so the refusal changes no state.
                if let Some((m, _)) = previous.and_then(|p| modes.mode_for(self.kind, p)) {
                    let _ = self.mgr.set_mode(m).await;
                    self.last_mode = Some(m.to_owned());
                }
                self.commanded = previous;
                return Err(refused(&e));
            }
        }
        if to == FlightState::Parking
            && previous == Some(FlightState::Taxi)
            && self.mgr.state().armed
        {
            // A plane parks on the ground disarmed: back from taxiing, the motor stops.
            if let Err(e) = self.mgr.arm(false).await {
                return Err(refused(&e));
            }
        }
        if to == FlightState::WaypointNavigation {
            // Entering AUTO puts the autopilot back to its default speed.
            self.speed_sent = Some(0.0);
            self.pass = PassWatch::starting_at(self.position);
            self.last_pending = None;
        }
        if to == FlightState::TakeOff && self.kind == VehicleKind::Copter {
            // NAV_TAKEOFF climbs to an altitude above home.
            let alt = self.takeoff_alt_above_home().unwrap_or(10.0);
            let takeoff = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, alt];
            if let Err(e) = self
                .mgr
                .command_long(MavCmd::MAV_CMD_NAV_TAKEOFF, takeoff)
                .await
            {
                return Err(refused(&e));
            }
        }
        if to != FlightState::ManualNavigation {
            // Give the sticks back to the RC transmitter.
            let _ = self.mgr.rc_override(rc_channels(self.kind, None)).await;
        }
        self.last_mode = Some(mode.to_owned());
        Ok(())
    }

    /// Puts a plane's landing on the autopilot ([`landing_mission`]) in place of the queue's
    /// window, from the approach on; the queue lays its window out afresh when navigation
    /// starts again.
    async fn lay_out_landing(&mut self) -> Result<(), String> {
        let home = self.home.ok_or("the autopilot's home is not known yet")?;
        let position = self.position.unwrap_or(home);
        self.forget_onboard();
        self.mgr
            .mission_upload(&landing_mission(home, position))
            .await
            .map_err(|e| e.to_string())?;
        self.mgr
            .mission_set_current(1)
            .await
            .map_err(|e| e.to_string())
    }

    /// The altitude a take-off climbs to, metres above home: the queue's first waypoint's
    /// (2 m at least); `None` with nothing queued.
    fn takeoff_alt_above_home(&self) -> Option<f32> {
        let above_home = |w: &Waypoint| match w.alt_ref {
            AltRef::Msl => w.alt - self.home_alt_msl.unwrap_or(0.0),
            AltRef::Relative | AltRef::Terrain => w.alt,
        };
        self.queue.target().map(|w| above_home(w).max(2.0) as f32)
    }

    /// Performs queue actions until the autopilot holds what it should.
    async fn prime(&mut self) -> Result<(), QueueError> {
        if self.mgr.partial_writes() == Some(false) && self.queue.partial_supported() {
            // The probe found none: whole windows from the start, no partial write tried.
            self.queue.partial_unsupported();
        }
        for _ in 0..32 {
            // Progress reported while the last action ran changes what is most urgent (the
            // wrap to slot 1 has one leg of slack): take it into account first.
            self.absorb_progress();
            let Some((action, layout)) = self.next_action() else {
                return Ok(());
            };
            let began = std::time::Instant::now();
            self.uploading = matches!(action, QueueAction::Upload(_));
            let outcome = self.exec_unless_wrap_due(&action, &layout).await;
            self.uploading = false;
            let Some(result) = outcome else {
                // Dropped mid-transfer: the autopilot commits a transfer only when it is
                // complete, so the abandoned write is simply redone after the wrap.
                tracing::debug!(
                    "queue: wrap due; action interrupted after {:?}",
                    began.elapsed()
                );
                continue;
            };
            tracing::debug!("queue: action took {:?}", began.elapsed());
            match result {
                Ok(()) => {
                    self.queue.done(&action);
                    if matches!(action, QueueAction::SetCurrent(_)) {
                        self.renumbered_target = false;
                    }
                    if matches!(action, QueueAction::Upload(_)) {
                        self.upload_took = began.elapsed();
                        let before = std::mem::replace(&mut self.markers, layout);
                        let c = self
                            .queue
                            .current_slot()
                            .filter(|_| self.queue.partial_supported());
                        if c.is_some_and(|c| before.seq(c) != self.markers.seq(c)) {
                            // The vehicle got to its target while the upload ran and drives to
                            // the slot whose marker it changed: the current item it kept names
                            // another item now. The restoring set-current goes out first.
                            tracing::debug!(
                                "queue: the upload renumbered the target: restoring it"
                            );
                            self.renumbered_target = true;
                            continue;
                        }
                        self.after_upload();
                        // What it reported meanwhile, judged against what it now holds.
                        if let Some(seq) = self.mgr.state().mission_current {
                            self.check_backtrack(self.markers.slot(seq));
                        }
                    }
                }
                Err(ExecError::PartialUnsupported) => self.queue.partial_unsupported(),
                Err(ExecError::Mission(e)) => return Err(QueueError::Mission(e)),
            }
        }
        Err(QueueError::Unsettled)
    }

    /// The queue's next action, with the layout of the mission it leaves on board; also the
    /// whole upload that puts DO_LAND_START markers where they were waiting to go (see
    /// [`Layout::next`]) once the queue itself has nothing to do.
    fn next_action(&self) -> Option<(QueueAction<Waypoint>, Layout)> {
        // Where the autopilot keeps its current item through an upload (it writes partially),
        // the target's number must not change under it, nor the next slot's when the vehicle
        // may get to its target (and on to that slot) before the upload ends.
        if let Some(slot) = self.queue.restore_due().filter(|_| self.index_stale()) {
            return Some((QueueAction::SetCurrent(slot), self.markers.clone()));
        }
        let fixed = self
            .queue
            .current_slot()
            .filter(|_| self.queue.partial_supported())
            .map(|c| c + u16::from(!self.upload_ends_before_the_target()));
        let Some(action) = self.queue.poll() else {
            let slots = self.queue.onboard()?;
            let layout = self.markers.next(&slots, fixed);
            return (layout != self.markers).then_some((QueueAction::Upload(slots), layout));
        };
        let after = match &action {
            QueueAction::SetCurrent(_) => return Some((action, self.markers.clone())),
            QueueAction::Upload(slots) => slots.clone(),
            QueueAction::WritePartial { start, items } => self.queue.mission_after(*start, items),
        };
        let layout = self.markers.next(&after, fixed);
        match action {
            // A marker coming or going moves every item after it: not a partial write.
            QueueAction::WritePartial { .. } if layout != self.markers => {
                Some((QueueAction::Upload(after), layout))
            }
            QueueAction::WritePartial { .. } => Some((action, self.markers.clone())),
            upload => Some((upload, layout)),
        }
    }

    /// Performs `action` (leaving the mission laid out as `layout`) while following the
    /// vehicle's progress; gives up on it (`None`) when that progress makes the wrap to slot 1
    /// due, which cannot wait for a slow transfer.
    async fn exec_unless_wrap_due(
        &mut self,
        action: &QueueAction<Waypoint>,
        layout: &Layout,
    ) -> Option<Result<(), ExecError>> {
        let mgr = Arc::clone(&self.mgr);
        let item0 = self.queue.target().cloned();
        if matches!(action, QueueAction::Upload(_)) {
            self.item0 = item0.clone();
        }
        let exec = exec(&mgr, self.home, item0.as_ref(), layout, action);
        tokio::pin!(exec);
        let mut listening = !matches!(action, QueueAction::SetCurrent(_));
        loop {
            tokio::select! {
                r = &mut exec => return Some(r),
                ev = self.mav.recv(), if listening => {
                    match ev {
                        Ok(ev) => {
                            self.absorb(ev);
                        }
                        Err(broadcast::error::RecvError::Lagged(n)) => {
                            tracing::warn!("APL lagged {n} MAVLink events; the tick resynchronises");
                            self.restorations_handled();
                        }
                        Err(broadcast::error::RecvError::Closed) => listening = false,
                    }
                    if matches!(self.queue.poll(), Some(QueueAction::SetCurrent(_))) {
                        return None;
                    }
                }
            }
        }
    }

    /// After a whole upload: the current item is restored next, unless the autopilot is one
    /// that keeps it (ArduPilot) and does not report item 0. A set-current there would only
    /// risk sending it back to a target it reached while the report was on its way (a slow
    /// radio), which is the very backtrack to avoid.
    fn after_upload(&mut self) {
        let s = self.mgr.state();
        if s.family.keeps_current_on_upload() && s.mission_current != Some(0) {
            self.queue.current_kept();
        }
    }

    /// Whether a whole upload started now ends (with room to spare) before the vehicle gets to
    /// its target, at its wall-clock speed and as long as the last upload took.
    fn upload_ends_before_the_target(&self) -> bool {
        let (Some(pos), Some(t)) = (self.position, self.queue.target()) else {
            return true;
        };
        self.wall_speed
            .eta(metres(pos, (t.lat, t.lon)))
            .is_none_or(|eta| eta > 3.0 * self.upload_took.as_secs_f64())
    }

    /// The autopilot's current item names another item than the one it drives to (see
    /// [`Self::renumbered_target`]) until the restoring set-current.
    fn index_stale(&self) -> bool {
        self.renumbered_target && self.queue.owes_restore()
    }

    /// What the autopilot holds is no longer known: the next upload lays it out afresh.
    fn forget_onboard(&mut self) {
        self.queue.forget_onboard();
        self.markers = Layout::default();
    }

    /// The vehicle reports it drives to `slot`: when that slot holds a waypoint already
    /// passed (or home), while in AUTO, it is driving back: counted, logged, and its current
    /// item set back to the target's slot next.
    fn check_backtrack(&mut self, slot: u16) {
        let s = self.mgr.state();
        let judged = backtracks_judged(
            s.mode_name,
            self.queue.is_running(),
            self.uploading,
            s.link_up,
            s.restorations == self.restorations_seen,
        );
        if !judged {
            return;
        }
        let Some(target) = self.queue.target().map(|w| w.seq) else {
            return;
        };
        let item0 = if s.family.item0_is_home() {
            None
        } else {
            self.item0.as_ref()
        };
        let back = self.queue.heads_back(slot, item0);
        if back {
            // Turned back to the target at once: the set-current goes out next.
            self.backtracks += 1;
            self.queue.restore_current();
            tracing::warn!(
                "backtrack #{}: the autopilot drives to slot {slot}, which holds home or a \
                 waypoint already passed; setting its current item back to the target \
                 (waypoint {target})",
                self.backtracks
            );
        }
    }

    async fn pump(&mut self) {
        let s = self.mgr.state();
        if self.failing || !s.link_up || s.restorations != self.restorations_seen {
            return;
        }
        if std::mem::take(&mut self.restart) {
            self.restart_navigation().await;
            return;
        }
        if let Err(e) = self.prime().await {
            tracing::warn!("rolling queue: {e}; retrying");
            let text = e.to_string();
            if e.is_refusal() && self.queue_error.as_deref() != Some(text.as_str()) {
                self.alarm(
                    Severity::Warning,
                    format!("rolling queue: refused: {text}; retrying"),
                );
                self.queue_error = Some(text);
            }
            self.failing = true;
            return;
        }
        self.queue_error = None;
        self.sync_speed().await;
    }

    /// The autopilot ended its mission early: wait (a heartbeat period or so) for it to leave
    /// AUTO for its end-of-mission mode, then enter WAYPOINT_NAVIGATION again, the window laid
    /// out afresh from slot 1 with the next waypoint; the VAL stays in WAYPOINT_NAVIGATION.
    async fn restart_navigation(&mut self) {
        let mut rx = self.mgr.watch_state();
        let wait = self
            .mgr
            .heartbeat_timeout()
            .min(Duration::from_millis(1500));
        let _ = tokio::time::timeout(wait, rx.wait_for(|s| s.mode_name != Some("AUTO"))).await;
        let left = self.queue.len();
        tracing::warn!("the autopilot ended its mission with {left} waypoints queued: restarting");
        self.last_mode = None;
        self.restarts_in_row = self.restarts_in_row.saturating_add(1);
        match self.change_state(FlightState::WaypointNavigation).await {
            Ok(()) => {
                self.restart_guard_until =
                    Some(std::time::Instant::now() + self.mgr.heartbeat_timeout());
                self.alarm(
                    Severity::Warning,
                    format!(
                        "the autopilot ended its mission early (a slot write came too late); \
                         navigation restarted with {left} waypoints left"
                    ),
                )
            }
            Err(e) if self.restarts_in_row < MAX_RESTARTS => {
                tracing::warn!("restarting navigation: {e}; retrying");
                self.restart = true;
            }
            Err(e) => {
                self.alarm(
                    Severity::Error,
                    format!("the autopilot ended its mission early; cannot restart: {e}"),
                );
                // Follow the autopilot's own mode, as for any other.
                self.check_mode();
            }
        }
    }

    fn reached(&mut self, w: Waypoint) {
        self.reached_at = Some(std::time::Instant::now());
        if self.queue.take_ended_early() && self.commanded == Some(FlightState::WaypointNavigation)
        {
            self.restart = true;
        } else {
            self.restarts_in_row = 0;
        }
        if self.mgr.family().advances_with_its_report() {
            // Its advance is done by the time we hear of the reach: nothing to wait for.
            self.queue.assume_advanced();
        }
        self.last_reached = Some(w.seq);
        self.pass.leg_from((w.lat, w.lon));
        self.emit(ApEvent::WaypointReached(WaypointReached {
            seq: w.seq,
            leg: w.leg,
            lat: w.lat,
            lon: w.lon,
            remaining: self.queue.len() as u64,
        }));
    }

    /// Takes the waypoint progress the manager reported so far into the queue, without
    /// acting on the autopilot; other events wait in `deferred` for the driver loop.
    fn absorb_progress(&mut self) {
        loop {
            match self.mav.try_recv() {
                Ok(ev) => {
                    self.absorb(ev);
                }
                Err(broadcast::error::TryRecvError::Lagged(n)) => {
                    tracing::warn!("APL lagged {n} MAVLink events; the tick resynchronises");
                    self.restorations_handled();
                }
                Err(_) => return,
            }
        }
    }

    /// Waypoint progress goes into the queue at once; anything else waits in `deferred`.
    /// Returns whether the queue should be pumped (progress or a new current item).
    fn absorb(&mut self, ev: MavEvent) -> bool {
        match ev {
            MavEvent::WaypointReached { seq, .. } => {
                self.reports_progress = true;
                if self.index_stale() {
                    tracing::debug!("reach of item {seq} before the restore: not taken");
                    return true;
                }
                let seq = self.markers.slot(seq);
                // Item 0 holds the target where item 0 is flown: an autopilot that reset its
                // current item by an upload and got there before the restoration reached the
                // target itself. Counted as such, the restoration then goes to the next slot,
                // not back to the target.
                let seq = match (self.queue.current_slot(), self.queue.target()) {
                    (Some(slot), Some(t))
                        if seq == 0
                            && !self.mgr.family().item0_is_home()
                            && self.item0.as_ref() == Some(t) =>
                    {
                        slot
                    }
                    _ => seq,
                };
                if let Some(w) = self.queue.on_reached(seq) {
                    self.reached(w);
                } else if self.last_pending.as_ref().is_some_and(|(s, _)| *s == seq) {
                    if let Some((_, w)) = self.last_pending.take() {
                        self.queue.discard();
                        self.reached(w);
                    }
                }
                true
            }
            MavEvent::MissionCurrent { seq } => {
                if self.index_stale() {
                    return true;
                }
                let slot = self.markers.slot(seq);
                self.check_backtrack(slot);
                // Also the autopilot's own advance after a reach, which a set-current waits for.
                if let Some(w) = self.queue.on_current(slot) {
                    self.reached(w);
                }
                true
            }
            MavEvent::Position(p) => {
                let progressed = self.progress_from_position(p.lat_deg, p.lon_deg);
                self.deferred.push_back(MavEvent::Position(p));
                progressed
            }
            ev => {
                self.deferred.push_back(ev);
                false
            }
        }
    }

    /// The fallback for autopilots that report no progress ([`PassWatch`]); also the last
    /// waypoint of a mission the autopilot ended there, its report late or lost.
    fn progress_from_position(&mut self, lat: f64, lon: f64) -> bool {
        self.position = Some((lat, lon));
        self.wall_speed
            .sample(std::time::Instant::now(), (lat, lon));
        if let Some((slot, w)) = self.last_pending.take() {
            // Also when the autopilot reports progress: it ended the mission at the last
            // waypoint (which is why it left AUTO), and its report may be lost on a radio.
            if self
                .pass
                .is_past((w.lat, w.lon), (lat, lon), self.radius_of(&w))
            {
                tracing::debug!("last waypoint {} reached (from position)", w.seq);
                self.queue.discard();
                self.reached(w);
                return true;
            }
            self.last_pending = Some((slot, w));
        }
        let (Some(slot), Some(w)) = (self.queue.current_slot(), self.queue.target()) else {
            self.pass.no_target();
            return false;
        };
        if self.reports_progress {
            return false;
        }
        let radius = self.radius_of(w);
        if !self.pass.sample(slot, (w.lat, w.lon), (lat, lon), radius) {
            return false;
        }
        match self.queue.on_reached(slot) {
            Some(w) => {
                tracing::debug!("waypoint {} reached (from position)", w.seq);
                // Inferred two samples past it: the autopilot's own advance is long done.
                self.queue.assume_advanced();
                self.reached(w);
                true
            }
            None => false,
        }
    }

    /// The acceptance radius of `w` on the autopilot, metres.
    fn radius_of(&self, w: &Waypoint) -> f64 {
        if w.fly_over {
            f64::from(FLY_OVER_RADIUS_M)
        } else {
            self.wp_radius()
        }
    }

    /// The autopilot's waypoint acceptance radius, metres (WP_RADIUS; Copter: WPNAV_RADIUS).
    fn wp_radius(&self) -> f64 {
        let r = match self.kind {
            VehicleKind::Copter => self.mgr.param_cached("WPNAV_RADIUS").map(|cm| cm / 100.0),
            _ => self.mgr.param_cached("WP_RADIUS"),
        };
        r.filter(|r| r.is_finite() && *r > 0.0)
            .map_or(2.0, f64::from)
    }

    /// The autopilot's default speed, for DO_CHANGE_SPEED back to it; -2 (MAVLink's "return
    /// to default") when the parameter is not known.
    fn default_speed(&self) -> f32 {
        let speed = match self.kind {
            VehicleKind::Rover => self.mgr.param_cached("CRUISE_SPEED"),
            VehicleKind::Copter => self.mgr.param_cached("WPNAV_SPEED").map(|cm| cm / 100.0),
            VehicleKind::Plane => self.mgr.param_cached("AIRSPEED_CRUISE"),
        };
        speed.filter(|s| s.is_finite() && *s > 0.0).unwrap_or(-2.0)
    }

    /// Commands the target waypoint's speed when it differs from the last one commanded.
    async fn sync_speed(&mut self) {
        let Some(w) = self.queue.target().filter(|_| self.queue.is_running()) else {
            return;
        };
        let want = wanted_speed(w);
        if self.speed_sent == Some(want) || self.speed_unsupported {
            return;
        }
        let speed = if want > 0.0 {
            want as f32
        } else {
            self.default_speed()
        };
        // Speed type: airspeed for a plane, ground speed otherwise; throttle unchanged.
        let kind = if self.kind == VehicleKind::Plane {
            0.0
        } else {
            1.0
        };
        let params = [kind, speed, -1.0, 0.0, 0.0, 0.0, 0.0];
        match self
            .mgr
            .command_long(MavCmd::MAV_CMD_DO_CHANGE_SPEED, params)
            .await
        {
            Ok(()) => self.speed_sent = Some(want),
            Err(
                e @ (CommandError::RetriesExhausted { .. }
                | CommandError::Rejected {
                    result: MavResult::MAV_RESULT_UNSUPPORTED,
                    ..
                }),
            ) => {
                self.speed_unsupported = true;
                self.alarm(
                    Severity::Warning,
                    format!(
                        "the autopilot does not take speed changes ({e}): the plan's speeds \
                         are not flown, the vehicle keeps its own"
                    ),
                );
            }
            Err(e @ CommandError::Rejected { .. }) => {
                // This value refused (out of the autopilot's range, say): not asked again
                // until the plan wants another.
                self.speed_sent = Some(want);
                self.alarm(
                    Severity::Warning,
                    format!("the autopilot refused the speed {speed} m/s: {e}"),
                );
            }
            Err(e) => tracing::warn!("setting speed {want} m/s: {e}; retrying"),
        }
    }

    /// Catches up with the autopilot from its latest state (after a lag, on every tick).
    async fn resync(&mut self) {
        if let Some(seq) = self
            .mgr
            .state()
            .mission_current
            .filter(|_| !self.index_stale())
        {
            if let Some(w) = self.queue.on_current(self.markers.slot(seq)) {
                self.reached(w);
            }
        }
        self.check_mode();
        self.pump().await;
    }

    /// Takes every link restoration the manager has seen as handled (the one just handled, or
    /// those lost when the event queue lagged: the tick resynchronises).
    fn restorations_handled(&mut self) {
        self.restorations_seen = self.mgr.state().restorations;
    }

    /// Whether this is an aircraft in a state that flies it (an aircraft's motors stop only on
    /// the ground: disarmed in one of these states, it has landed).
    fn was_flying(&self) -> bool {
        use FlightState::*;
        self.kind != VehicleKind::Rover
            && matches!(
                self.commanded,
                Some(
                    TakeOff
                        | WaypointNavigation
                        | Directed
                        | ManualNavigation
                        | ReturnToLaunch
                        | Landing
                )
            )
    }

    /// Reacts to the autopilot's latest mode when it is not the one commanded.
    fn check_mode(&mut self) {
        let s = self.mgr.state();
        let Some(mode) = s.mode_name.filter(|_| s.link_up) else {
            return;
        };
        if s.restorations != self.restorations_seen {
            // The state already shows an autopilot that came back (a restarted one starts in
            // its default mode) while the loss and the restoration still wait in our queue:
            // handling the restoration (re-reading, resuming what was commanded) comes first,
            // or its boot mode would read as a pilot's choice.
            return;
        }
        if self.last_mode.as_deref() == Some(mode) {
            return;
        }
        if self.early_end_mode(mode) {
            // The end-of-mission mode of an early end: navigation is being restarted.
            return;
        }
        self.last_mode = Some(mode.to_owned());
        if self.commanded.is_none() {
            // Still in CONFIGURE_CHECK: the VAL has not taken the autopilot over yet.
            return;
        }
        if mode != "AUTO" && self.queue.is_running() {
            self.stop_queue_keeping_last();
        }
        let modes = self.modes();
        let expected = self.commanded.and_then(|st| modes.mode_for(self.kind, st));
        if expected.map(|m| m.0) != Some(mode) {
            let state = modes.state_for_mode(self.kind, mode);
            if state.is_some() {
                self.commanded = state;
            }
            self.emit(ApEvent::ModeChanged {
                mode: mode.to_owned(),
                state,
            });
        }
    }

    /// Stops the queue; its last waypoint, if it was flying to it, is kept (`last_pending`), so
    /// that a reach reported after the stop still counts.
    fn stop_queue_keeping_last(&mut self) {
        if self.queue.is_running() {
            if let (1, Some(slot), Some(w)) = (
                self.queue.len(),
                self.queue.current_slot(),
                self.queue.target(),
            ) {
                self.last_pending = Some((slot, w.clone()));
            }
        }
        self.queue.stop();
    }

    async fn on_mav(&mut self, ev: MavEvent) {
        match ev {
            ev @ (MavEvent::WaypointReached { .. } | MavEvent::MissionCurrent { .. }) => {
                self.absorb(ev);
                self.pump().await;
            }
            MavEvent::ModeChanged { .. } | MavEvent::ArmedChanged { .. } => {
                self.check_mode();
                self.emit(ApEvent::Status(status_of(&self.mgr)));
                if matches!(ev, MavEvent::ArmedChanged { armed: false }) && self.was_flying() {
                    self.emit(ApEvent::Landed);
                }
                // Arming sets the home again (ArduPilot, PX4).
                if matches!(ev, MavEvent::ArmedChanged { armed: true }) {
                    request_home(&self.mgr);
                }
            }
            MavEvent::Heartbeat { .. } => self.emit(ApEvent::Status(status_of(&self.mgr))),
            // A detector's report is a detection, not an alarm.
            MavEvent::StatusText { severity, text } => {
                if let Some(e) = telemetry::status_text(severity, &text) {
                    self.emit(e);
                }
            }
            MavEvent::Position(p) => {
                // Progress from it was taken when it was absorbed.
                self.home.get_or_insert((p.lat_deg, p.lon_deg));
                self.home_alt_msl = Some(telemetry::home_alt_msl(&p));
                self.emit(ApEvent::Position(telemetry::position(&p)));
            }
            MavEvent::Home(h) => {
                self.home = Some((h.lat, h.lon));
                self.emit(ApEvent::Home(h));
            }
            MavEvent::Attitude(a) => self.emit(ApEvent::Attitude(telemetry::attitude(&a))),
            MavEvent::VfrHud(v) => self.emit(ApEvent::Speeds(telemetry::speeds(&v))),
            MavEvent::LinkLost => {
                self.alarm(Severity::Critical, "autopilot heartbeat lost");
                self.emit(ApEvent::LinkLost);
                self.emit(ApEvent::Status(status_of(&self.mgr)));
            }
            MavEvent::LinkRestored => {
                self.restorations_handled();
                self.on_restored().await
            }
            MavEvent::MissionChangedElsewhere {
                system_id,
                component_id,
            } => self.on_mission_changed(system_id, component_id).await,
            MavEvent::SysStatus(s) => {
                self.emit(ApEvent::Battery(telemetry::battery_of_sys_status(&s)));
            }
            MavEvent::BatteryStatus(b) => {
                if let Some(battery) = telemetry::battery_of_status(&b) {
                    self.emit(ApEvent::Battery(battery));
                }
            }
            MavEvent::Connected { .. } => {}
        }
    }

    /// Another ground station wrote the mission: do not fight it. The queue stops feeding the
    /// autopilot (and forgets what it held), the mission is read back and reported.
    async fn on_mission_changed(&mut self, system_id: u8, component_id: u8) {
        let by = format!("MAVLink system {system_id} component {component_id}");
        self.queue.stop();
        self.forget_onboard();
        self.last_pending = None;
        self.alarm(
            Severity::Warning,
            format!(
                "mission changed by another ground station ({by}): following it, the queue stopped"
            ),
        );
        let waypoints = match self.mgr.mission_download().await {
            Ok(items) => items
                .iter()
                .enumerate()
                .map(|(i, m)| Waypoint {
                    seq: i as u64,
                    lat: m.lat_deg(),
                    lon: m.lon_deg(),
                    alt: f64::from(m.z),
                    leg: "external".into(),
                    ..Waypoint::default()
                })
                .collect(),
            Err(e) => {
                tracing::warn!("reading back the mission another station wrote: {e}");
                Vec::new()
            }
        };
        tracing::info!("mission changed by {by}: {} items", waypoints.len());
        self.emit(ApEvent::MissionChanged(MissionChanged { by, waypoints }));
        self.emit(ApEvent::Status(status_of(&self.mgr)));
    }

    /// Heartbeats are back: re-read parameters and mission, and resume what was commanded.
    async fn on_restored(&mut self) {
        self.alarm(Severity::Notice, "autopilot heartbeat restored");
        // Perhaps another autopilot, or the same rebooted: learn again what it reports.
        self.reports_progress = false;
        self.speed_unsupported = false;
        match self.mgr.params_list().await {
            Ok(p) => tracing::info!("re-read {} parameters", p.len()),
            Err(e) => tracing::warn!("re-reading parameters: {e}"),
        }
        probe_partial(&self.mgr).await;
        if self.mgr.partial_writes() == Some(true) {
            self.queue.partial_supported_again();
        }
        let intact = match self.mgr.mission_download().await {
            Ok(onboard) => {
                let expected: Option<Vec<MissionItem>> =
                    self.queue.onboard().map(|v| self.markers.items(&v));
                matches!(expected, Some(e) if e.len() + 1 == onboard.len()
                    && e.iter().zip(&onboard[1..]).all(|(a, b)| same_item(a, b)))
            }
            Err(e) => {
                tracing::warn!("downloading the mission: {e}");
                false
            }
        };
        if !intact {
            self.forget_onboard();
        }
        let mode = self.mgr.state().mode_name;
        if let Some(state) = self.commanded {
            let wanted = self.modes().mode_for(self.kind, state).map(|m| m.0);
            // Still in the commanded mode (the link dropped, the autopilot flew on): only the
            // queue may need priming again, which changes no state.
            let reprime = state == FlightState::WaypointNavigation && !intact && mode == wanted;
            // In another mode: the autopilot rebooted (or someone changed it meanwhile).
            // Putting it back re-arms and moves the vehicle: only when configured to, and
            // announced; otherwise the operator decides.
            let moved = wanted.is_some() && mode != wanted;
            if moved && !self.resume_after_reboot {
                self.queue.stop();
                self.last_pending = None;
                self.last_mode = None;
                self.alarm(
                    Severity::Critical,
                    format!(
                        "autopilot came back in {} (rebooted?) while {state} was commanded: \
                         not resuming it (resumeAfterReboot is off); the operator must restart {state}",
                        mode.unwrap_or("an unknown mode")
                    ),
                );
                // The VAL follows the state the autopilot now reports.
                self.restorations_handled();
                self.check_mode();
            } else if reprime || moved {
                self.last_mode = None;
                tracing::info!("autopilot is in {mode:?}: resuming {state}");
                let why = if moved {
                    "after the autopilot came back (resumeAfterReboot)"
                } else {
                    "after the link came back"
                };
                match self.change_state(state).await {
                    Ok(()) => self.alarm(
                        if moved {
                            Severity::Warning
                        } else {
                            Severity::Notice
                        },
                        format!("resumed {state} {why}"),
                    ),
                    Err(e) => self.alarm(Severity::Error, format!("cannot resume {state}: {e}")),
                }
            }
        }
        self.emit(ApEvent::LinkRestored);
        self.emit(ApEvent::Status(status_of(&self.mgr)));
    }
}
