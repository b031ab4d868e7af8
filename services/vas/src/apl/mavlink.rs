//! The MAVLink autopilot layer every family shares (003 §3.3.3): USAL states to the family's
//! modes, telemetry and alarms from the MAVLink manager, and the rolling waypoint queue kept
//! fed.
//!
//! One driver task owns the [`RollingQueue`]: it receives the VAL's commands and the
//! manager's events in order, performs the queue's actions on the autopilot and retries them
//! on a tick when they fail. Its duties follow the seed's objects: `AP_Navigation` (modes,
//! queue), `AP_Reader` (telemetry, status texts, mode changes), `AP_Parameters` (read at
//! start and after every reconnection).
//!
//! This file holds the configuration and the [`MavlinkAutopilot`] handle (the
//! [`IAutopilot`] side); `driver` is the task; the pure parts beside it are `items`
//! (waypoints to mission items, the landing, sticks to PWM), `layout` (queue slots to
//! mission sequence numbers, DO_LAND_START markers between them), `progress` (waypoints passed,
//! backtracks judged), `telemetry` (reports in USAL's units) and `fence`. What differs per
//! family is an [`ApFamily`] ([`super::ardupilot::ArduPilotModes`],
//! [`super::px4::Px4Modes`]): [`MavlinkAutopilot::open`] takes the family the
//! configuration names, or the heartbeat's when it names none.

use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;

use async_trait::async_trait;
use tokio::sync::{broadcast, mpsc, oneshot};
use tokio::time::interval;
use tokio_util::sync::CancellationToken;
use tokio_util::task::TaskTracker;
use usal_types::{
    Alarm, AltRef, AutopilotStatus, DirectedTarget, FlightState, ManualControl, MissionChanged,
    QueueStatus, Severity, VehicleCommand, VehicleKind, Waypoint, WaypointKind, WaypointReached,
};

use super::queue::{QueueAction, RollingQueue};
use super::{check_room, family_modes, ApEvent, ApFamily, Arming, AutopilotError, IAutopilot};
use crate::mavlink_cm::dialect::{MavCmd, MavFrame, MavResult};
use crate::mavlink_cm::{
    CommandError, ManagerConfig, ManagerOpenError, MavEvent, MavlinkManager, MissionError,
    MissionItem, MissionStage, Telemetry,
};

mod driver;
mod fence;
mod items;
mod layout;
mod progress;
mod telemetry;

use driver::{configure, Driver};
pub use items::FLY_OVER_RADIUS_M;
use items::*;
use layout::Layout;

/// Settings of the MAVLink autopilot layer.
#[derive(Clone, Debug)]
pub struct MavlinkApConfig {
    /// Vehicle kind (decides the mode table).
    pub vehicle: VehicleKind,
    /// Rolling-queue slots on the autopilot (after home), ≥ 3.
    pub queue_slots: u16,
    /// Position, attitude and speed telemetry rate, Hz.
    pub telemetry_hz: f32,
    /// SYS_STATUS and MISSION_CURRENT rate, Hz.
    pub status_hz: f32,
    /// The MAVLink manager's tuning.
    pub manager: ManagerConfig,
    /// After the autopilot comes back in another mode (a reboot), put it back in the state
    /// the VAL had commanded, re-arming if needed (`resumeAfterReboot`). Off: the VAL follows
    /// the state the autopilot reports and an alarm asks the operator to restart.
    pub resume_after_reboot: bool,
}

impl Default for MavlinkApConfig {
    fn default() -> Self {
        Self {
            vehicle: VehicleKind::Rover,
            queue_slots: 5,
            telemetry_hz: 4.0,
            status_hz: 1.0,
            manager: ManagerConfig::default(),
            resume_after_reboot: false,
        }
    }
}

/// Errors opening the MAVLink autopilot layer.
#[derive(Debug, thiserror::Error)]
pub enum MavlinkApOpenError {
    /// Bad endpoint.
    #[error(transparent)]
    Manager(#[from] ManagerOpenError),
    /// Bad queue size.
    #[error(transparent)]
    Queue(#[from] super::QueueCreateError),
}

enum Cmd {
    ChangeState(FlightState, oneshot::Sender<Result<(), AutopilotError>>),
    DirectTo([f64; 4], oneshot::Sender<Result<(), AutopilotError>>),
    Push(
        Vec<Waypoint>,
        u64,
        oneshot::Sender<Result<QueueStatus, AutopilotError>>,
    ),
    Clear(oneshot::Sender<QueueStatus>),
    Status(oneshot::Sender<QueueStatus>),
    Command(VehicleCommand, oneshot::Sender<Result<(), AutopilotError>>),
}

/// The MAVLink implementation of [`IAutopilot`], for every family (its modes an [`ApFamily`]).
pub struct MavlinkAutopilot {
    mgr: Arc<MavlinkManager>,
    cfg: MavlinkApConfig,
    cmd_tx: mpsc::Sender<Cmd>,
    events_tx: broadcast::Sender<ApEvent>,
    cancel: CancellationToken,
    tasks: TaskTracker,
}

impl MavlinkAutopilot {
    /// Opens the MAVLink endpoint (`udpout:HOST:PORT`, `serial:PATH:BAUD`...) and starts the
    /// layer's driver. Call [`IAutopilot::listen_ap`] next. The family's modes are those the
    /// configuration names (`cfg.manager.family`, which also fixes the manager's mission
    /// conventions), else the heartbeat's.
    ///
    /// # Errors
    /// A malformed endpoint or queue size.
    pub async fn open(endpoint: &str, cfg: MavlinkApConfig) -> Result<Self, MavlinkApOpenError> {
        let modes = cfg.manager.family.map(family_modes);
        let queue = RollingQueue::new(cfg.queue_slots)?;
        let mgr = Arc::new(MavlinkManager::open(endpoint, cfg.manager.clone()).await?);
        let (cmd_tx, cmd_rx) = mpsc::channel(64);
        let (events_tx, _) = broadcast::channel(1024);
        let cancel = CancellationToken::new();
        let tasks = TaskTracker::new();
        let mut driver = Driver::new(mgr.clone(), cfg.vehicle, queue, events_tx.clone(), modes);
        driver.resume_after_reboot = cfg.resume_after_reboot;
        tasks.spawn(driver.run(cmd_rx, cancel.clone()));
        tasks.close();
        Ok(Self {
            mgr,
            cfg,
            cmd_tx,
            events_tx,
            cancel,
            tasks,
        })
    }

    /// The MAVLink manager underneath (parameters, raw commands).
    pub fn manager(&self) -> &MavlinkManager {
        &self.mgr
    }

    async fn ask<T>(
        &self,
        make: impl FnOnce(oneshot::Sender<T>) -> Cmd,
    ) -> Result<T, AutopilotError> {
        let (tx, rx) = oneshot::channel();
        self.cmd_tx
            .send(make(tx))
            .await
            .map_err(|_| AutopilotError::Stopped)?;
        rx.await.map_err(|_| AutopilotError::Stopped)
    }
}

/// A parameter operation's failure as the operator reads it (an unknown name goes unanswered
/// by ArduPilot: said so).
fn param_error(e: crate::mavlink_cm::ParamError) -> AutopilotError {
    use crate::mavlink_cm::ParamError;
    match e {
        ParamError::RetriesExhausted { name, .. } => AutopilotError::Refused(format!(
            "no answer for parameter {name}: the autopilot has no such parameter, or the link is down"
        )),
        other => AutopilotError::Refused(other.to_string()),
    }
}

fn status_of(mgr: &MavlinkManager) -> AutopilotStatus {
    telemetry::status(&mgr.state())
}

#[async_trait]
impl IAutopilot for MavlinkAutopilot {
    fn vehicle(&self) -> VehicleKind {
        self.cfg.vehicle
    }

    fn events(&self) -> broadcast::Receiver<ApEvent> {
        self.events_tx.subscribe()
    }

    fn status(&self) -> AutopilotStatus {
        status_of(&self.mgr)
    }

    async fn listen_ap(&self) -> Result<(), AutopilotError> {
        let wait = self.cfg.manager.connect_wait;
        self.mgr
            .wait_connected(wait)
            .await
            .map_err(|e| AutopilotError::NotConnected(e.to_string()))?;
        configure(&self.mgr, &self.cfg).await?;
        let _ = self.events_tx.send(ApEvent::Configured);
        Ok(())
    }

    async fn change_state(&self, to: FlightState) -> Result<(), AutopilotError> {
        self.ask(|tx| Cmd::ChangeState(to, tx)).await?
    }

    async fn push_waypoints(
        &self,
        wps: Vec<Waypoint>,
        max_queued: u64,
    ) -> Result<QueueStatus, AutopilotError> {
        let terrain = self.mgr.param_cached("TERRAIN_ENABLE");
        if let Some(why) = altitude_refusal(self.cfg.vehicle, terrain, &wps) {
            return Err(AutopilotError::Unsupported(why));
        }
        self.ask(|tx| Cmd::Push(wps, max_queued, tx)).await?
    }

    async fn clear_waypoints(&self) -> Result<QueueStatus, AutopilotError> {
        self.ask(Cmd::Clear).await
    }

    async fn queue_status(&self) -> Result<QueueStatus, AutopilotError> {
        self.ask(Cmd::Status).await
    }

    async fn manual_navigation(&self, mc: Option<ManualControl>) -> Result<(), AutopilotError> {
        self.mgr
            .rc_override(rc_channels(self.cfg.vehicle, mc.as_ref()))
            .await
            .map_err(|e| AutopilotError::NotConnected(e.to_string()))
    }

    async fn command(&self, cmd: VehicleCommand) -> Result<(), AutopilotError> {
        self.ask(|tx| Cmd::Command(cmd, tx)).await?
    }

    async fn direct_to(
        &self,
        lat: f64,
        lon: f64,
        alt: f32,
        speed: f32,
    ) -> Result<(), AutopilotError> {
        let target = [lat, lon, f64::from(alt), f64::from(speed)];
        self.ask(|tx| Cmd::DirectTo(target, tx)).await?
    }

    async fn shutdown(&self) {
        self.cancel.cancel();
        self.tasks.wait().await;
    }

    async fn get_param(&self, name: &str) -> Result<f32, AutopilotError> {
        self.mgr.param_get(name).await.map_err(param_error)
    }

    async fn set_param(&self, name: &str, value: f32) -> Result<f32, AutopilotError> {
        self.mgr.param_set(name, value).await.map_err(param_error)
    }

    async fn list_params(&self) -> Result<Vec<(String, f32)>, AutopilotError> {
        let all = self.mgr.params_list().await.map_err(param_error)?;
        Ok(all.into_iter().collect())
    }

    async fn read_mission(&self, first: u16, last: u16) -> Result<Vec<Waypoint>, AutopilotError> {
        let items = self
            .mgr
            .mission_download_range(first, last)
            .await
            .map_err(|e| match e {
                MissionError::Link(l) => AutopilotError::NotConnected(l.to_string()),
                other => AutopilotError::Refused(other.to_string()),
            })?;
        Ok(items
            .iter()
            .zip(first..)
            .map(|(m, seq)| Waypoint {
                seq: u64::from(seq),
                lat: m.lat_deg(),
                lon: m.lon_deg(),
                alt: f64::from(m.z),
                leg: "autopilot".into(),
                ..Waypoint::default()
            })
            .collect())
    }

    async fn upload_fence(&self, f: Option<&usal_types::Fence>) -> Result<(), AutopilotError> {
        let wait = self.cfg.manager.connect_wait;
        self.mgr
            .wait_connected(wait)
            .await
            .map_err(|e| AutopilotError::NotConnected(e.to_string()))?;
        // Each family keeps its fence its own way; another autopilot would leave each unknown
        // parameter unanswered through every retry.
        match self.mgr.family() {
            crate::mavlink_cm::AutopilotFamily::ArduPilot => fence::upload(&self.mgr, f).await,
            crate::mavlink_cm::AutopilotFamily::Px4 => fence::upload_px4(&self.mgr, f).await,
            other => Err(AutopilotError::Unsupported(format!(
                "fences are uploaded to ArduPilot and PX4 only, this autopilot is {other:?}"
            ))),
        }
    }
}

impl Drop for MavlinkAutopilot {
    fn drop(&mut self) {
        self.cancel.cancel();
    }
}
