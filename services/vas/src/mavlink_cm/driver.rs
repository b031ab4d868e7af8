//! The manager's driver task and shared state: it owns the connection, decodes frames into the
//! [`VehicleState`], the parameter cache and the reach detector, publishes [`MavEvent`]s, sends
//! our GCS heartbeat, watches the autopilot's and reopens the endpoint when the transport
//! fails. Requests reach the wire through it (see [`Inner::send`], [`Inner::transact`]).

use std::collections::BTreeMap;
use std::io;
use std::sync::{Arc, Mutex as StdMutex};
use std::time::Duration;

use marea::sync::lock;
use mavconn::{Connection, Counters, Endpoint, Frame, OpenOptions};
use mavlink::dialects::ardupilotmega::{
    MavAutopilot, MavCmd, MavMessage, MavMissionResult, MavMissionType, MavModeFlag, MavState,
    MavType, BATTERY_STATUS_DATA, COMMAND_LONG_DATA, HEARTBEAT_DATA, REQUEST_DATA_STREAM_DATA,
};
use mavlink::MavHeader;
use tokio::sync::{broadcast, mpsc, watch};
use tokio::time::{interval, sleep, timeout, timeout_at, Instant};
use tokio_util::sync::CancellationToken;

use super::family::AutopilotFamily;
use super::manager::{ManagerConfig, Telemetry, VehicleState};
use super::modes;
use super::outbound::Outbound;
use super::param::{param_name, ParamCache};
use super::reach::{ReachDetector, ReachSource};
use super::types::*;

/// What the manager handle, the request methods and the driver task share.
pub(crate) struct Inner {
    pub(crate) cfg: ManagerConfig,
    pub(crate) out_tx: mpsc::Sender<Outbound>,
    pub(crate) raw_tx: broadcast::Sender<Arc<MavMessage>>,
    pub(crate) events_tx: broadcast::Sender<MavEvent>,
    pub(crate) state_tx: watch::Sender<VehicleState>,
    pub(crate) params: StdMutex<ParamCache>,
    pub(crate) mission: StdMutex<Vec<MissionItem>>,
    pub(crate) reach: StdMutex<ReachDetector>,
    /// Requested rates, re-applied after the link comes back: (telemetry, Hz, via REQUEST_DATA_STREAM).
    pub(crate) rates: StdMutex<BTreeMap<Telemetry, (f32, bool)>>,
    pub(crate) ops: tokio::sync::Mutex<()>,
    /// Parse errors and drops, summed over every reopening of the connection.
    pub(crate) counters: Arc<Counters>,
    /// MISSION_WRITE_PARTIAL_LIST works on this connection: `None` until probed; forgotten
    /// when the link comes back (perhaps another autopilot, or the same one updated).
    pub(crate) partial: StdMutex<Option<bool>>,
    /// Every autopilot frame with its header, for the forward endpoints.
    pub(crate) frames_tx: broadcast::Sender<Arc<(MavHeader, MavMessage)>>,
}

/// Waits until `matcher` accepts a message or `deadline` passes (`Ok(None)`).
pub(crate) async fn wait_for<T>(
    rx: &mut broadcast::Receiver<Arc<MavMessage>>,
    deadline: Instant,
    mut matcher: impl FnMut(&MavMessage) -> Option<T>,
) -> Result<Option<T>, LinkError> {
    loop {
        match timeout_at(deadline, rx.recv()).await {
            Err(_) => return Ok(None),
            Ok(Ok(m)) => {
                if let Some(t) = matcher(&m) {
                    return Ok(Some(t));
                }
            }
            Ok(Err(broadcast::error::RecvError::Lagged(_))) => {}
            Ok(Err(broadcast::error::RecvError::Closed)) => return Err(LinkError::Closed),
        }
    }
}

impl Inner {
    /// Hands one [`Outbound`] to the driver.
    pub(crate) async fn put(&self, out: Outbound) -> Result<(), LinkError> {
        self.out_tx.send(out).await.map_err(|_| LinkError::Closed)
    }

    /// Hands one message to the driver.
    pub(crate) async fn send(&self, msg: MavMessage) -> Result<(), LinkError> {
        self.put(Outbound::Message(msg)).await
    }

    /// Before a resend: lets a stream receiver stuck on a corrupted length field give up on
    /// it (see [`Outbound::Resync`]).
    pub(crate) async fn resync(&self) -> Result<(), LinkError> {
        self.put(Outbound::Resync).await
    }

    /// The autopilot's (system, component), waiting up to `connect_wait` for its first heartbeat.
    pub(crate) async fn target(&self) -> Result<(u8, u8), LinkError> {
        let mut rx = self.state_tx.subscribe();
        let wait = self.cfg.connect_wait;
        let result = timeout(wait, rx.wait_for(|s| s.system_id.is_some()))
            .await
            .map(|r| r.map(|s| (s.system_id.unwrap_or(1), s.component_id.unwrap_or(1))));
        match result {
            Ok(Ok(target)) => Ok(target),
            Ok(Err(_)) => Err(LinkError::Closed),
            Err(_) => Err(LinkError::NotConnected(wait)),
        }
    }

    /// Sends `make(attempt)` until `matcher` accepts an answer; `Ok(None)` when
    /// every attempt timed out.
    pub(crate) async fn transact<T>(
        &self,
        make: impl Fn(u32) -> MavMessage,
        matcher: impl FnMut(&MavMessage) -> Option<T>,
    ) -> Result<Option<T>, LinkError> {
        self.transact_copies(1, make, matcher).await
    }

    /// [`Self::transact`] sending each attempt `copies` times back to back: for idempotent,
    /// time-critical requests, where a duplicate costs a few bytes and a loss a whole timeout.
    pub(crate) async fn transact_copies<T>(
        &self,
        copies: u32,
        make: impl Fn(u32) -> MavMessage,
        mut matcher: impl FnMut(&MavMessage) -> Option<T>,
    ) -> Result<Option<T>, LinkError> {
        let mut rx = self.raw_tx.subscribe();
        for attempt in 0..self.cfg.retries {
            if attempt > 0 {
                self.resync().await?;
            }
            for _ in 0..copies.max(1) {
                self.send(make(attempt)).await?;
            }
            let deadline = Instant::now() + self.cfg.request_timeout;
            if let Some(t) = wait_for(&mut rx, deadline, &mut matcher).await? {
                return Ok(Some(t));
            }
        }
        Ok(None)
    }

    #[allow(deprecated)]
    pub(crate) async fn request_stream(&self, kind: Telemetry, hz: f32) -> Result<(), LinkError> {
        let target = self.target().await?;
        self.send(MavMessage::REQUEST_DATA_STREAM(REQUEST_DATA_STREAM_DATA {
            req_message_rate: hz.round().clamp(0.0, f32::from(u16::MAX)) as u16,
            target_system: target.0,
            target_component: target.1,
            req_stream_id: kind.stream(),
            start_stop: u8::from(hz > 0.0),
        }))
        .await
    }

    pub(crate) fn emit(&self, e: MavEvent) {
        let _ = self.events_tx.send(e);
    }

    pub(crate) fn reached(&self, seq: Option<u16>, source: ReachSource) {
        if let Some(seq) = seq {
            self.emit(MavEvent::WaypointReached { seq, source });
        }
    }

    pub(crate) fn link_lost(&self) {
        let mut was_up = false;
        self.state_tx.send_modify(|s| {
            was_up = s.link_up;
            s.link_up = false;
        });
        if was_up {
            self.emit(MavEvent::LinkLost);
        }
    }

    /// Handles one frame; returns true when the link just came (back) up.
    pub(crate) fn on_frame(&self, frame: Frame, last_hb: &mut Option<Instant>) -> bool {
        let Frame { header, msg, .. } = frame;
        if self.frames_tx.receiver_count() > 0 {
            let _ = self.frames_tx.send(Arc::new((header, msg.clone())));
        }
        let (sys, comp) = (header.system_id as u8, header.component_id);
        let known = {
            let s = self.state_tx.borrow();
            s.system_id.zip(s.component_id)
        };
        let mut came_up = false;
        if let MavMessage::HEARTBEAT(hb) = &msg {
            // Several vehicles, and several components of one vehicle (camera, gimbal,
            // companion computer), may share the link: the configured system and component,
            // else the first autopilot heard.
            let wanted = self.cfg.target_system.is_none_or(|t| t == sys)
                && self.cfg.target_component.is_none_or(|c| c == comp);
            if mavconn::is_autopilot_heartbeat(hb)
                && wanted
                && known.is_none_or(|k| k == (sys, comp))
            {
                *last_hb = Some(Instant::now());
                came_up = self.on_heartbeat(sys, comp, hb);
            }
        }
        // Anything else from another system or component is not the autopilot's (it still
        // reaches the forward endpoints above).
        if known.is_some_and(|k| k != (sys, comp)) || (known.is_none() && !came_up) {
            return came_up;
        }
        match &msg {
            MavMessage::STATUSTEXT(t) => {
                let text = t.text.to_str().unwrap_or("").to_owned();
                let reached = lock(&self.reach).on_status_text(&text);
                self.emit(MavEvent::StatusText {
                    severity: t.severity,
                    text,
                });
                self.reached(reached, ReachSource::StatusText);
            }
            MavMessage::MISSION_ACK(a)
                if a.mavtype == MavMissionResult::MAV_MISSION_ACCEPTED
                    && a.mission_type == MavMissionType::MAV_MISSION_TYPE_MISSION
                    && a.target_system != 0
                    && a.target_system != self.cfg.system_id =>
            {
                // The autopilot accepted a mission transfer of another ground station.
                self.emit(MavEvent::MissionChangedElsewhere {
                    system_id: a.target_system,
                    component_id: a.target_component,
                });
            }
            MavMessage::AUTOPILOT_VERSION(v) => {
                let bits = v.capabilities.bits();
                self.state_tx.send_modify(|s| s.capabilities = Some(bits));
            }
            MavMessage::MISSION_ITEM_REACHED(r) => {
                let reached = lock(&self.reach).on_item_reached(r.seq);
                self.reached(reached, ReachSource::ItemReached);
            }
            MavMessage::MISSION_CURRENT(c) => {
                let changed = self.state_tx.borrow().mission_current != Some(c.seq);
                self.state_tx
                    .send_modify(|s| s.mission_current = Some(c.seq));
                let reached = lock(&self.reach).on_mission_current(c.seq);
                self.reached(reached, ReachSource::MissionCurrent);
                if changed {
                    self.emit(MavEvent::MissionCurrent { seq: c.seq });
                }
            }
            MavMessage::PARAM_VALUE(v) => {
                let mut cache = lock(&self.params);
                cache.count = Some(v.param_count);
                cache.values.insert(
                    param_name(&v.param_id),
                    (v.param_value, v.param_type, v.param_index),
                );
            }
            MavMessage::GLOBAL_POSITION_INT(p) => self.emit(MavEvent::Position(Position {
                lat_deg: f64::from(p.lat) / 1e7,
                lon_deg: f64::from(p.lon) / 1e7,
                alt_msl_m: p.alt as f32 / 1000.0,
                alt_rel_m: p.relative_alt as f32 / 1000.0,
                vel_ned: [
                    f32::from(p.vx) / 100.0,
                    f32::from(p.vy) / 100.0,
                    f32::from(p.vz) / 100.0,
                ],
                heading_deg: (p.hdg != u16::MAX).then(|| f32::from(p.hdg) / 100.0),
                time_boot_ms: p.time_boot_ms,
            })),
            MavMessage::HOME_POSITION(h) => self.emit(MavEvent::Home(usal_types::Home {
                lat: f64::from(h.latitude) / 1e7,
                lon: f64::from(h.longitude) / 1e7,
                alt: f64::from(h.altitude) / 1000.0,
            })),
            MavMessage::ATTITUDE(a) => self.emit(MavEvent::Attitude(Attitude {
                roll: a.roll,
                pitch: a.pitch,
                yaw: a.yaw,
                rates: [a.rollspeed, a.pitchspeed, a.yawspeed],
            })),
            MavMessage::VFR_HUD(v) => self.emit(MavEvent::VfrHud(VfrHud {
                airspeed: v.airspeed,
                groundspeed: v.groundspeed,
                alt_m: v.alt,
                climb: v.climb,
                heading_deg: v.heading,
                throttle_pct: v.throttle,
            })),
            MavMessage::BATTERY_STATUS(b) => self.emit(MavEvent::BatteryStatus(battery_status(b))),
            MavMessage::SYS_STATUS(s) => self.emit(MavEvent::SysStatus(SysStatus {
                voltage_v: f32::from(s.voltage_battery) / 1000.0,
                current_a: (s.current_battery >= 0).then(|| f32::from(s.current_battery) / 100.0),
                battery_pct: u8::try_from(s.battery_remaining).ok(),
                load_pct: f32::from(s.load) / 10.0,
                unhealthy_sensors: (s.onboard_control_sensors_present.bits()
                    & !s.onboard_control_sensors_health.bits()),
            })),
            _ => {}
        }
        let _ = self.raw_tx.send(Arc::new(msg));
        came_up
    }

    pub(crate) fn on_heartbeat(&self, sys: u8, comp: u8, hb: &HEARTBEAT_DATA) -> bool {
        let armed = hb
            .base_mode
            .contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED);
        let family = self
            .cfg
            .family
            .unwrap_or_else(|| AutopilotFamily::from_heartbeat(hb.autopilot));
        // A generic autopilot tells its encoding by the number: ArduPilot's are below 256,
        // PX4's main mode sits in the third byte.
        let before_px4 = self.state_tx.borrow().px4_modes;
        let px4_modes = family.px4_modes()
            || (family == AutopilotFamily::Generic && (before_px4 || hb.custom_mode > 0xFFFF));
        let name = if px4_modes {
            modes::px4_name(hb.custom_mode)
        } else {
            modes::name(hb.mavtype, hb.custom_mode)
        };
        let before = self.state_tx.borrow().clone();
        if !before.link_up {
            *lock(&self.partial) = None;
        }
        self.state_tx.send_modify(|s| {
            s.link_up = true;
            s.autopilot = Some(hb.autopilot);
            s.family = family;
            s.px4_modes = px4_modes;
            s.system_id = Some(sys);
            s.component_id = Some(comp);
            s.vehicle_type = Some(hb.mavtype);
            s.mode = Some(hb.custom_mode);
            s.mode_name = name;
            s.armed = armed;
            s.system_status = Some(hb.system_status);
            if before.system_id.is_some() && !before.link_up {
                s.restorations = s.restorations.wrapping_add(1);
            }
        });
        if before.system_id.is_none() {
            self.emit(MavEvent::Connected {
                system_id: sys,
                component_id: comp,
                vehicle_type: hb.mavtype,
            });
        } else if !before.link_up {
            lock(&self.reach).reset();
            self.emit(MavEvent::LinkRestored);
        }
        self.emit(MavEvent::Heartbeat {
            mode: hb.custom_mode,
            mode_name: name,
            armed,
            system_status: hb.system_status,
        });
        if before.mode != Some(hb.custom_mode) {
            self.emit(MavEvent::ModeChanged {
                from: before.mode,
                to: hb.custom_mode,
                name,
            });
        }
        if before.system_id.is_some() && before.armed != armed {
            self.emit(MavEvent::ArmedChanged { armed });
        }
        !before.link_up
    }

    /// Messages that re-apply the requested telemetry rates after a reconnection.
    #[allow(deprecated)]
    pub(crate) fn rate_messages(&self, target: (u8, u8)) -> Vec<MavMessage> {
        lock(&self.rates)
            .iter()
            .map(|(kind, &(hz, via_stream))| {
                if via_stream {
                    MavMessage::REQUEST_DATA_STREAM(REQUEST_DATA_STREAM_DATA {
                        req_message_rate: hz.round().clamp(0.0, f32::from(u16::MAX)) as u16,
                        target_system: target.0,
                        target_component: target.1,
                        req_stream_id: kind.stream(),
                        start_stop: u8::from(hz > 0.0),
                    })
                } else {
                    MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                        param1: kind.message_id() as f32,
                        param2: if hz > 0.0 { 1e6 / hz } else { -1.0 },
                        command: MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL,
                        target_system: target.0,
                        target_component: target.1,
                        ..Default::default()
                    })
                }
            })
            .collect()
    }
}

fn gcs_heartbeat() -> MavMessage {
    MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode: 0,
        mavtype: MavType::MAV_TYPE_GCS,
        autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
        base_mode: MavModeFlag::empty(),
        system_status: MavState::MAV_STATE_ACTIVE,
        mavlink_version: 3,
    })
}

/// The task that owns the connection; ends when `cancel` fires or the manager is dropped.
pub(crate) async fn driver(
    inner: Arc<Inner>,
    endpoint: Endpoint,
    mut out_rx: mpsc::Receiver<Outbound>,
    cancel: CancellationToken,
) {
    let mut header = MavHeader {
        system_id: u32::from(inner.cfg.system_id),
        component_id: inner.cfg.component_id,
        sequence: 0,
    };
    let mut last_hb: Option<Instant> = None;
    let backoff = inner.cfg.reconnect_backoff;
    let opts = OpenOptions {
        counters: inner.counters.clone(),
        signing: inner.cfg.signing.clone(),
        pin: inner.cfg.pin.clone(),
        ..OpenOptions::default()
    };
    loop {
        let opened = tokio::select! {
            _ = cancel.cancelled() => return,
            c = Connection::open(&endpoint, opts.clone()) => c,
        };
        let mut conn = match opened {
            Ok(c) => c,
            Err(e) => {
                tracing::debug!("cannot open {endpoint}: {e}");
                tokio::select! {
                    _ = cancel.cancelled() => return,
                    _ = sleep(backoff) => continue,
                }
            }
        };
        tracing::debug!("opened {endpoint}");
        let mut send = |conn: &mut Connection, msg: &MavMessage| -> io::Result<()> {
            let r = conn.send(header, msg).map_err(io::Error::from);
            header.sequence = header.sequence.wrapping_add(1);
            r
        };
        let mut gcs_hb = interval(Duration::from_secs(1));
        let mut watchdog = interval(Duration::from_millis(100));
        let error: io::Error = loop {
            tokio::select! {
                biased;
                _ = cancel.cancelled() => return,
                frame = conn.recv() => match frame {
                    Some(Ok(frame)) => {
                        if inner.on_frame(frame, &mut last_hb) {
                            let target = {
                                let s = inner.state_tx.borrow();
                                (s.system_id.unwrap_or(1), s.component_id.unwrap_or(1))
                            };
                            for msg in inner.rate_messages(target) {
                                if let Err(e) = send(&mut conn, &msg) {
                                    tracing::debug!("re-applying rates: {e}");
                                }
                            }
                        }
                    }
                    Some(Err(e)) => break e,
                    None => break io::ErrorKind::BrokenPipe.into(),
                },
                out = out_rx.recv() => match out {
                    Some(Outbound::Message(msg)) => if let Err(e) = send(&mut conn, &msg) { break e },
                    Some(Outbound::Resync) => if let Err(e) = conn.resync() { break e.into() },
                    Some(Outbound::Raw(h, msg)) => if let Err(e) = conn.send(h, &msg) { break e.into() },
                    None => return,
                },
                _ = gcs_hb.tick() => if let Err(e) = send(&mut conn, &gcs_heartbeat()) { break e },
                _ = watchdog.tick() => {
                    if last_hb.is_some_and(|t| t.elapsed() > inner.cfg.heartbeat_timeout) {
                        inner.link_lost();
                    }
                }
            }
        };
        tracing::warn!("MAVLink link {endpoint} failed: {error}; reopening");
        inner.link_lost();
        drop(conn);
        tokio::select! {
            _ = cancel.cancelled() => return,
            _ = sleep(backoff) => {}
        }
    }
}

/// BATTERY_STATUS in SI units: cells marked absent (`u16::MAX`) are left out of the voltage.
pub(crate) fn battery_status(b: &BATTERY_STATUS_DATA) -> BatteryStatus {
    let cells: Vec<f32> = b
        .voltages
        .iter()
        .filter(|&&mv| mv != u16::MAX)
        .map(|&mv| f32::from(mv) / 1000.0)
        .collect();
    BatteryStatus {
        id: b.id,
        voltage_v: (!cells.is_empty()).then(|| cells.iter().sum()),
        current_a: (b.current_battery >= 0).then(|| f32::from(b.current_battery) / 100.0),
        battery_pct: u8::try_from(b.battery_remaining).ok(),
    }
}

#[cfg(test)]
mod battery_tests {
    use super::*;

    #[test]
    fn battery_status_sums_the_cells_present_and_says_what_is_unknown() {
        let mut voltages = [u16::MAX; 10];
        voltages[..3].copy_from_slice(&[4100, 4150, 4200]);
        let b = battery_status(&BATTERY_STATUS_DATA {
            voltages,
            current_battery: 1250,
            battery_remaining: 76,
            ..BATTERY_STATUS_DATA::DEFAULT
        });
        assert_eq!(b.id, 0);
        assert!((b.voltage_v.unwrap() - 12.45).abs() < 1e-4, "{b:?}");
        assert_eq!(b.current_a, Some(12.5));
        assert_eq!(b.battery_pct, Some(76));
        let unknown = battery_status(&BATTERY_STATUS_DATA {
            voltages: [u16::MAX; 10],
            current_battery: -1,
            battery_remaining: -1,
            ..BATTERY_STATUS_DATA::DEFAULT
        });
        assert_eq!(
            (unknown.voltage_v, unknown.current_a, unknown.battery_pct),
            (None, None, None)
        );
    }
}
