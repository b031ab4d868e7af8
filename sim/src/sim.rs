//! The async driver: runs a [`Vehicle`] on a [`Link`] in accelerated time.
//!
//! Time model: the vehicle is integrated at a fixed simulated step; every wall
//! tick runs as many steps as `speedup × wall elapsed` requires. A tick that comes
//! late (a loaded machine descheduled the process) counts for at most
//! [`MAX_WALL_PER_TICK`]: simulated time pauses during a stall instead of jumping
//! ahead, so a ground station that was waiting on us is not left behind the vehicle. Heartbeats and
//! telemetry streams are paced in *wall* time (a rate of 4 Hz is 4 messages per
//! real second whatever the speed-up), so a ground station neither times out nor
//! drowns; MISSION_ITEM_REACHED, STATUSTEXT and MISSION_CURRENT changes are sent
//! the moment they happen in simulated time.

use std::io;
use std::path::PathBuf;
use std::time::{Duration, Instant};

use mavlink::dialects::ardupilotmega::MavMessage;
use tokio::sync::watch;
use tokio_util::sync::CancellationToken;
use usal_types::camera::CameraPose;

use crate::camera::CameraView;
use crate::link::{Link, LinkConfig, LinkInfo, LinkOpenError};
use crate::log::{LogRecord, LogWriter};
use crate::vehicle::{Vehicle, VehicleConfig};

/// Simulated seconds per integration step.
pub const STEP_S: f64 = 0.02;
/// Wall period of the driver loop.
const TICK: Duration = Duration::from_millis(10);
/// Bound on steps per tick so a stalled machine degrades to slower time instead of freezing.
const MAX_STEPS_PER_TICK: u32 = 20_000;
/// Wall time one tick may account for, however late it comes.
const MAX_WALL_PER_TICK: Duration = Duration::from_millis(50);

/// Everything needed to start a simulator.
#[derive(Clone, Debug)]
pub struct SimConfig {
    /// The vehicle.
    pub vehicle: VehicleConfig,
    /// The transport.
    pub link: LinkConfig,
    /// Simulated seconds per wall second (≥ 0.01).
    pub speedup: f64,
    /// JSON-lines event log, if wanted.
    pub log: Option<PathBuf>,
    /// Report no mission progress (see [`Vehicle::set_quiet_progress`]).
    pub quiet_progress: bool,
    /// Seconds (simulated) the autopilot answers mode changes and arming "temporarily
    /// rejected" (see [`Vehicle::set_not_ready_for`]).
    pub not_ready_s: f64,
    /// Seconds (simulated) between reporting a waypoint reached and moving the current item
    /// on (see [`Vehicle::set_late_advance`]); 0: at once.
    pub late_advance_s: f64,
    /// A steady wind: speed (m/s) and the direction it blows from (degrees).
    pub wind: (f64, f64),
    /// MAVLink 2 signing: sign everything, accept only correctly signed frames.
    pub signing: Option<mavconn::Signing>,
    /// Which autopilot's conventions to follow (see [`crate::profile`]).
    pub autopilot: crate::profile::Profile,
    /// The battery (see [`Vehicle::set_battery`]).
    pub battery: crate::battery::BatteryConfig,
    /// Most items one fence transfer may have (see [`Vehicle::set_fence_capacity`];
    /// [`crate::fence::DEFAULT_CAPACITY`] unless told otherwise).
    pub fence_capacity: u16,
}

/// Errors of the simulator.
#[derive(Debug, thiserror::Error)]
pub enum SimError {
    /// The transport could not be opened.
    #[error(transparent)]
    LinkOpen(#[from] LinkOpenError),
    /// The transport failed while running.
    #[error("link I/O error: {0}")]
    LinkIo(io::Error),
    /// The log file could not be created or written.
    #[error("log file {path}: {source}")]
    Log {
        /// Log path.
        path: PathBuf,
        /// Cause.
        source: io::Error,
    },
}

/// The vehicle `cfg` describes, as it starts.
fn vehicle_of(cfg: &SimConfig, now: Instant) -> Vehicle {
    let mut vehicle = Vehicle::new(cfg.vehicle, now);
    vehicle.set_quiet_progress(cfg.quiet_progress);
    vehicle.set_not_ready_for(cfg.not_ready_s);
    vehicle.set_late_advance(cfg.late_advance_s);
    vehicle.set_wind(cfg.wind.0, cfg.wind.1);
    vehicle.set_profile(cfg.autopilot);
    vehicle.set_battery(cfg.battery);
    vehicle.set_fence_capacity(cfg.fence_capacity);
    vehicle
}

/// An opened simulator, ready to run.
pub struct Simulator {
    cfg: SimConfig,
    vehicle: Vehicle,
    link: Link,
    log: Option<LogWriter>,
    /// Points of interest the vehicle reports when it passes them.
    detector: Option<crate::detector::Detector>,
    /// The camera's view of the vehicle, updated each tick, and its field of view.
    camera: Option<(watch::Sender<CameraView>, f64)>,
}

impl Simulator {
    /// Opens the link and the log file.
    ///
    /// # Errors
    /// When the link or the log file cannot be opened.
    pub async fn open(cfg: SimConfig) -> Result<Self, SimError> {
        let log = match &cfg.log {
            Some(path) => Some(LogWriter::create(path).map_err(|source| SimError::Log {
                path: path.clone(),
                source,
            })?),
            None => None,
        };
        let link = Link::open_signed(&cfg.link, cfg.vehicle.sysid, cfg.signing.clone()).await?;
        let vehicle = vehicle_of(&cfg, Instant::now());
        Ok(Self {
            cfg,
            vehicle,
            link,
            log,
            detector: None,
            camera: None,
        })
    }

    /// A camera of field of view `hfov_deg` under the vehicle: the view it follows, updated
    /// each tick (see [`crate::camera`]).
    pub fn camera_view(&mut self, hfov_deg: f64) -> watch::Receiver<CameraView> {
        let (tx, rx) = watch::channel(self.view(hfov_deg));
        self.camera = Some((tx, hfov_deg));
        rx
    }

    fn view(&self, hfov_deg: f64) -> CameraView {
        let at = self.vehicle.position();
        let geo = self.vehicle.frame().to_geo(at);
        CameraView {
            at,
            pose: CameraPose {
                lat: geo.lat_deg,
                lon: geo.lon_deg,
                height_m: at.up,
                heading_deg: self.vehicle.heading_deg(),
                hfov_deg,
            },
        }
    }

    /// Carries `detector`: each point it newly sees after a step goes out as a STATUSTEXT
    /// (see [`crate::detector`]).
    pub fn set_detector(&mut self, detector: crate::detector::Detector) {
        self.detector = Some(detector);
    }

    fn detect(&mut self) {
        let Some(d) = self.detector.as_mut() else {
            return;
        };
        for (poi, confidence) in d.check(self.vehicle.position()) {
            let text = crate::detector::detection_text(&poi, confidence);
            tracing::info!(poi = poi.id, "detected: {text}");
            self.link.send(&crate::detector::statustext(&text));
        }
    }

    /// What the link opened (bound UDP address, pty slave path...).
    pub fn link_info(&self) -> &LinkInfo {
        self.link.info()
    }

    /// Sends `out` once the log holds what led to it: a test that reads the log when it sees a
    /// message's effect (a reached waypoint, the mode after the mission) finds the events
    /// behind it. (Sent first, on a loaded host the log lagged: the VAS saw HOLD after the last
    /// waypoint while the log did not yet say it was reached.)
    fn send_logged(&mut self, out: Vec<MavMessage>) -> Result<(), SimError> {
        self.flush_log()?;
        for msg in out {
            self.link.send(&msg);
        }
        Ok(())
    }

    fn flush_log(&mut self) -> Result<(), SimError> {
        let events = self.vehicle.take_log();
        if let Some(writer) = self.log.as_mut() {
            for (t_sim, event) in events {
                writer
                    .write(&LogRecord { t_sim, event })
                    .map_err(|source| SimError::Log {
                        path: self.cfg.log.clone().unwrap_or_default(),
                        source,
                    })?;
            }
        }
        Ok(())
    }

    /// Runs until `shutdown` is cancelled or the link fails.
    ///
    /// # Errors
    /// When the link fails or the log cannot be written.
    pub async fn run(mut self, shutdown: CancellationToken) -> Result<(), SimError> {
        let result = self.run_loop(&shutdown).await;
        tracing::info!(
            parse_errors = self.link.parse_errors(),
            dropped = self.link.dropped(),
            rejected_signatures = self.link.rejected_signatures(),
            sim_time = self.vehicle.sim_time(),
            "mavsim stopped"
        );
        self.link.close().await;
        result
    }

    async fn run_loop(&mut self, shutdown: &CancellationToken) -> Result<(), SimError> {
        let speedup = self.cfg.speedup.max(0.01);
        let mut last_tick = Instant::now();
        let mut target = 0.0;
        let mut tick = tokio::time::interval(TICK);
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        self.flush_log()?;
        loop {
            tokio::select! {
                biased;
                _ = shutdown.cancelled() => return Ok(()),
                inbound = self.link.recv() => {
                    let inbound = match inbound {
                        Some(Ok(i)) => i,
                        Some(Err(e)) => return Err(SimError::LinkIo(e)),
                        None => return Err(SimError::LinkIo(io::ErrorKind::BrokenPipe.into())),
                    };
                    let from = (inbound.header.system_id as u8, inbound.header.component_id);
                    let out = self.vehicle.handle(from, &inbound.msg, Instant::now());
                    self.send_logged(out)?;
                }
                _ = tick.tick() => {
                    let now = Instant::now();
                    let wall = now.duration_since(last_tick).min(MAX_WALL_PER_TICK);
                    last_tick = now;
                    target += wall.as_secs_f64() * speedup;
                    let mut steps = 0;
                    while self.vehicle.sim_time() + STEP_S / 2.0 < target && steps < MAX_STEPS_PER_TICK {
                        let out = self.vehicle.step(STEP_S);
                        self.send_logged(out)?;
                        steps += 1;
                        self.detect();
                    }
                    // Too slow to keep up: time runs slower rather than owing a burst.
                    target = target.min(self.vehicle.sim_time() + STEP_S);
                    let out = self.vehicle.poll(now);
                    self.send_logged(out)?;
                    if let Some((tx, hfov)) = &self.camera {
                        tx.send_replace(self.view(*hfov));
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::kinematics::{GeoPoint, VehicleKind};
    use crate::profile::Profile;
    use mavlink::dialects::ardupilotmega::{MavMissionResult, MavMissionType, MISSION_COUNT_DATA};

    /// The options reach the vehicle: here the profile (PX4's geofence parameters) and the
    /// fence capacity (a larger fence transfer is refused with NO_SPACE).
    #[test]
    fn the_config_reaches_the_vehicle() {
        let cfg = SimConfig {
            vehicle: VehicleConfig {
                kind: VehicleKind::Rover,
                sysid: 1,
                home: GeoPoint {
                    lat_deg: 41.2757,
                    lon_deg: 1.9881,
                    alt_m: 10.0,
                },
            },
            link: LinkConfig::Pty,
            speedup: 1.0,
            log: None,
            quiet_progress: false,
            not_ready_s: 0.0,
            late_advance_s: 0.0,
            wind: (0.0, 0.0),
            signing: None,
            autopilot: Profile::Px4,
            battery: crate::battery::BatteryConfig::default(),
            fence_capacity: 2,
        };
        let mut v = vehicle_of(&cfg, Instant::now());
        assert_eq!(v.profile(), Profile::Px4);
        let count = |v: &mut Vehicle, count| {
            v.handle(
                (255, 190),
                &MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
                    count,
                    target_system: 1,
                    mission_type: MavMissionType::MAV_MISSION_TYPE_FENCE,
                    ..Default::default()
                }),
                Instant::now(),
            )
        };
        assert!(matches!(count(&mut v, 3).as_slice(),
            [MavMessage::MISSION_ACK(a)] if a.mavtype == MavMissionResult::MAV_MISSION_NO_SPACE));
        assert!(matches!(
            count(&mut v, 2).as_slice(),
            [MavMessage::MISSION_REQUEST_INT(_)]
        ));
    }
}
