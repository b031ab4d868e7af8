//! [`MavlinkManager`]: one async handle on one autopilot (003 §3.2.2).
//!
//! A driver task owns the connection: it decodes frames, keeps the
//! [`VehicleState`], the parameter cache and the reach detector up to date,
//! publishes [`MavEvent`]s, sends our GCS heartbeat, watches the autopilot's,
//! and reopens the endpoint when the transport fails. Requests (commands,
//! parameters, mission transfers) run in the caller's task: they subscribe to
//! the raw message stream, send through the driver and wait with a per-attempt
//! timeout and a bounded number of retries. Mission and parameter
//! transactions are serialised so two callers cannot interleave on the wire.

use std::collections::BTreeMap;
use std::io;
use std::sync::{Arc, Mutex as StdMutex};
use std::time::Duration;

use mavconn::{Connection, Counters, Endpoint, Frame, OpenOptions};
use mavlink::dialects::ardupilotmega::{
    MavAutopilot, MavCmd, MavDataStream, MavMessage, MavMissionResult, MavModeFlag, MavParamType,
    MavResult, MavState, MavType, COMMAND_LONG_DATA, HEARTBEAT_DATA, MISSION_ACK_DATA,
    MISSION_CLEAR_ALL_DATA, MISSION_COUNT_DATA, MISSION_REQUEST_INT_DATA,
    MISSION_REQUEST_LIST_DATA, MISSION_SET_CURRENT_DATA, MISSION_WRITE_PARTIAL_LIST_DATA,
    PARAM_REQUEST_LIST_DATA, PARAM_REQUEST_READ_DATA, PARAM_SET_DATA, RC_CHANNELS_OVERRIDE_DATA,
    REQUEST_DATA_STREAM_DATA,
};
use mavlink::MavHeader;
use tokio::sync::{broadcast, mpsc, watch};
use tokio::task::JoinHandle;
use tokio::time::{interval, sleep, timeout, timeout_at, Instant};
use tokio_util::sync::CancellationToken;

use super::modes::{self, ModeSpec};
use super::reach::{ReachDetector, ReachSource};
use super::types::*;

/// Tuning of the manager.
#[derive(Clone, Debug)]
pub struct ManagerConfig {
    /// Our MAVLink system id (255: a ground station).
    pub system_id: u8,
    /// Our component id (190: MAV_COMP_ID_MISSIONPLANNER).
    pub component_id: u8,
    /// No autopilot heartbeat for this long means the link is lost.
    pub heartbeat_timeout: Duration,
    /// How long one attempt of a request waits for its answer.
    pub request_timeout: Duration,
    /// Attempts per request (and per mission item) before giving up.
    pub retries: u32,
    /// Pause between attempts to reopen a failed transport.
    pub reconnect_backoff: Duration,
    /// How long a request waits for the first heartbeat before failing.
    pub connect_wait: Duration,
}

impl Default for ManagerConfig {
    fn default() -> Self {
        Self {
            system_id: 255,
            component_id: 190,
            heartbeat_timeout: Duration::from_secs(3),
            request_timeout: Duration::from_millis(1000),
            retries: 5,
            reconnect_backoff: Duration::from_millis(500),
            connect_wait: Duration::from_secs(10),
        }
    }
}

/// What the manager knows of the autopilot, from its heartbeats.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct VehicleState {
    /// Heartbeats are arriving.
    pub link_up: bool,
    /// Autopilot system id, once seen.
    pub system_id: Option<u8>,
    /// Autopilot component id, once seen.
    pub component_id: Option<u8>,
    /// Vehicle type, once seen.
    pub vehicle_type: Option<MavType>,
    /// Custom (ArduPilot) mode.
    pub mode: Option<u32>,
    /// Its ArduPilot name.
    pub mode_name: Option<&'static str>,
    /// Armed flag.
    pub armed: bool,
    /// MAV_STATE (the thesis' "AutopilotState").
    pub system_status: Option<MavState>,
    /// Last MISSION_CURRENT.
    pub mission_current: Option<u16>,
}

/// A telemetry message the manager can request at a rate.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Telemetry {
    /// GLOBAL_POSITION_INT.
    Position,
    /// ATTITUDE.
    Attitude,
    /// VFR_HUD.
    VfrHud,
    /// SYS_STATUS.
    SysStatus,
    /// MISSION_CURRENT.
    MissionCurrent,
}

impl Telemetry {
    fn message_id(self) -> u32 {
        match self {
            Self::Position => 33,
            Self::Attitude => 30,
            Self::VfrHud => 74,
            Self::SysStatus => 1,
            Self::MissionCurrent => 42,
        }
    }

    #[allow(deprecated)] // REQUEST_DATA_STREAM is the fallback for autopilots without SET_MESSAGE_INTERVAL.
    fn stream(self) -> MavDataStream {
        match self {
            Self::Position => MavDataStream::MAV_DATA_STREAM_POSITION,
            Self::Attitude => MavDataStream::MAV_DATA_STREAM_EXTRA1,
            Self::VfrHud => MavDataStream::MAV_DATA_STREAM_EXTRA2,
            Self::SysStatus | Self::MissionCurrent => {
                MavDataStream::MAV_DATA_STREAM_EXTENDED_STATUS
            }
        }
    }
}

#[derive(Default)]
struct ParamCache {
    values: BTreeMap<String, (f32, MavParamType, u16)>,
    count: Option<u16>,
}

struct Inner {
    cfg: ManagerConfig,
    out_tx: mpsc::Sender<Outbound>,
    raw_tx: broadcast::Sender<Arc<MavMessage>>,
    events_tx: broadcast::Sender<MavEvent>,
    state_tx: watch::Sender<VehicleState>,
    params: StdMutex<ParamCache>,
    mission: StdMutex<Vec<MissionItem>>,
    reach: StdMutex<ReachDetector>,
    /// Requested rates, re-applied after the link comes back: (telemetry, Hz, via REQUEST_DATA_STREAM).
    rates: StdMutex<BTreeMap<Telemetry, (f32, bool)>>,
    ops: tokio::sync::Mutex<()>,
    /// Parse errors and drops, summed over every reopening of the connection.
    counters: Arc<Counters>,
}

use marea::sync::lock;

fn param_name(id: &mavlink::types::CharArray<16>) -> String {
    id.to_str().unwrap_or("").to_owned()
}

/// The MAVLink communication manager: one autopilot, any transport.
pub struct MavlinkManager {
    inner: Arc<Inner>,
    cancel: CancellationToken,
    driver: Option<JoinHandle<()>>,
}

impl MavlinkManager {
    /// Starts talking to the autopilot at `endpoint` (`udpout:HOST:PORT`,
    /// `udpin:ADDR:PORT`, `tcpout:HOST:PORT`, `serial:PATH[:BAUD]`). Returns at
    /// once; the connection is (re)opened in the background.
    ///
    /// # Errors
    /// When the endpoint string is malformed.
    pub async fn open(endpoint: &str, cfg: ManagerConfig) -> Result<Self, ManagerOpenError> {
        let endpoint: Endpoint = endpoint.parse()?;
        let (out_tx, out_rx) = mpsc::channel(256);
        let (raw_tx, _) = broadcast::channel(1024);
        let (events_tx, _) = broadcast::channel(1024);
        let inner = Arc::new(Inner {
            cfg,
            out_tx,
            raw_tx,
            events_tx,
            state_tx: watch::Sender::new(VehicleState::default()),
            params: StdMutex::default(),
            mission: StdMutex::default(),
            reach: StdMutex::default(),
            rates: StdMutex::default(),
            ops: tokio::sync::Mutex::new(()),
            counters: Arc::default(),
        });
        let cancel = CancellationToken::new();
        let driver = tokio::spawn(driver(inner.clone(), endpoint, out_rx, cancel.clone()));
        Ok(Self {
            inner,
            cancel,
            driver: Some(driver),
        })
    }

    /// Stops the driver and closes the transport.
    pub async fn shutdown(mut self) {
        self.cancel.cancel();
        if let Some(driver) = self.driver.take() {
            let _ = driver.await;
        }
    }

    /// Every event from now on. A slow receiver loses the oldest events (`Lagged`).
    pub fn subscribe(&self) -> broadcast::Receiver<MavEvent> {
        self.inner.events_tx.subscribe()
    }

    /// The latest vehicle state.
    pub fn state(&self) -> VehicleState {
        self.inner.state_tx.borrow().clone()
    }

    /// A watch on the vehicle state.
    pub fn watch_state(&self) -> watch::Receiver<VehicleState> {
        self.inner.state_tx.subscribe()
    }

    /// Frames that passed the CRC but could not be decoded.
    pub fn parse_errors(&self) -> u64 {
        self.inner.counters.parse_errors()
    }

    /// Waits for the link to be up (an autopilot heartbeat).
    ///
    /// # Errors
    /// [`LinkError::NotConnected`] after `wait`.
    pub async fn wait_connected(&self, wait: Duration) -> Result<VehicleState, LinkError> {
        let mut rx = self.inner.state_tx.subscribe();
        let result = timeout(wait, rx.wait_for(|s| s.link_up))
            .await
            .map(|r| r.map(|s| s.clone()));
        match result {
            Ok(Ok(s)) => Ok(s),
            Ok(Err(_)) => Err(LinkError::Closed),
            Err(_) => Err(LinkError::NotConnected(wait)),
        }
    }

    // ------------------------------------------------------------ commands

    /// Sends COMMAND_LONG and checks its COMMAND_ACK, retrying on silence.
    ///
    /// # Errors
    /// No ACK after the retries, or an ACK other than ACCEPTED.
    pub async fn command_long(
        &self,
        command: MavCmd,
        params: [f32; 7],
    ) -> Result<(), CommandError> {
        let target = self.inner.target().await?;
        let make = |attempt: u32| {
            MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
                param1: params[0],
                param2: params[1],
                param3: params[2],
                param4: params[3],
                param5: params[4],
                param6: params[5],
                param7: params[6],
                command,
                target_system: target.0,
                target_component: target.1,
                confirmation: attempt.min(255) as u8,
            })
        };
        let matcher = |m: &MavMessage| match m {
            MavMessage::COMMAND_ACK(a) if a.command == command => Some(a.result),
            _ => None,
        };
        match self.inner.transact(make, matcher).await? {
            Some(MavResult::MAV_RESULT_ACCEPTED) => Ok(()),
            Some(result) => Err(CommandError::Rejected { command, result }),
            None => Err(CommandError::RetriesExhausted {
                command,
                attempts: self.inner.cfg.retries,
            }),
        }
    }

    async fn confirm(
        &self,
        what: String,
        f: impl Fn(&VehicleState) -> bool,
    ) -> Result<(), CommandError> {
        let mut rx = self.inner.state_tx.subscribe();
        let result = timeout(self.inner.cfg.heartbeat_timeout, rx.wait_for(f))
            .await
            .map(|r| r.map(|_| ()));
        match result {
            Ok(Ok(())) => Ok(()),
            Ok(Err(_)) => Err(LinkError::Closed.into()),
            Err(_) => Err(CommandError::NotConfirmed(what)),
        }
    }

    /// Changes the flight mode (ArduPilot name such as `"AUTO"`, or number),
    /// checks the COMMAND_ACK and waits for a heartbeat showing it.
    ///
    /// # Errors
    /// Unknown name, refusal, no answer, or no confirming heartbeat.
    pub async fn set_mode(&self, mode: impl Into<ModeSpec>) -> Result<(), CommandError> {
        self.inner.target().await?;
        let number = match mode.into() {
            ModeSpec::Number(n) => n,
            ModeSpec::Name(name) => {
                let vehicle = self
                    .state()
                    .vehicle_type
                    .unwrap_or(MavType::MAV_TYPE_GENERIC);
                modes::number(vehicle, &name).ok_or(CommandError::UnknownMode(name))?
            }
        };
        let custom = f32::from(MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED.bits());
        self.command_long(
            MavCmd::MAV_CMD_DO_SET_MODE,
            [custom, number as f32, 0.0, 0.0, 0.0, 0.0, 0.0],
        )
        .await?;
        self.confirm(format!("mode {number}"), |s| s.mode == Some(number))
            .await
    }

    /// Arms (`true`) or disarms, checks the ACK and waits for the heartbeat to agree.
    ///
    /// # Errors
    /// Refusal, no answer, or no confirming heartbeat.
    pub async fn arm(&self, arm: bool) -> Result<(), CommandError> {
        let p1 = if arm { 1.0 } else { 0.0 };
        self.command_long(
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            [p1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        )
        .await?;
        self.confirm(format!("armed={arm}"), |s| s.armed == arm)
            .await
    }

    /// Overrides RC channels 1-8 (PWM µs; 0 releases a channel, 65535 leaves it
    /// unchanged). Fire and forget: resend at the pilot's rate.
    ///
    /// # Errors
    /// Not connected, or shut down.
    pub async fn rc_override(&self, channels: [u16; 8]) -> Result<(), LinkError> {
        let target = self.inner.target().await?;
        let [c1, c2, c3, c4, c5, c6, c7, c8] = channels;
        self.inner
            .send(MavMessage::RC_CHANNELS_OVERRIDE(
                RC_CHANNELS_OVERRIDE_DATA {
                    chan1_raw: c1,
                    chan2_raw: c2,
                    chan3_raw: c3,
                    chan4_raw: c4,
                    chan5_raw: c5,
                    chan6_raw: c6,
                    chan7_raw: c7,
                    chan8_raw: c8,
                    target_system: target.0,
                    target_component: target.1,
                },
            ))
            .await
    }

    /// Requests telemetry at `rates` (Hz; 0 stops it) with SET_MESSAGE_INTERVAL,
    /// falling back to REQUEST_DATA_STREAM where the autopilot refuses or ignores
    /// it. The rates are re-applied whenever the link comes back.
    ///
    /// # Errors
    /// Only when not connected: the fallback has no acknowledgement to check.
    pub async fn request_telemetry(&self, rates: &[(Telemetry, f32)]) -> Result<(), CommandError> {
        for &(kind, hz) in rates {
            let interval_us = if hz > 0.0 { 1e6 / hz } else { -1.0 };
            let params = [
                kind.message_id() as f32,
                interval_us,
                0.0,
                0.0,
                0.0,
                0.0,
                0.0,
            ];
            let via_stream = match self
                .command_long(MavCmd::MAV_CMD_SET_MESSAGE_INTERVAL, params)
                .await
            {
                Ok(()) => false,
                Err(CommandError::Link(e)) => return Err(e.into()),
                Err(e) => {
                    tracing::debug!(
                        "SET_MESSAGE_INTERVAL for {kind:?} failed ({e}); using REQUEST_DATA_STREAM"
                    );
                    self.inner.request_stream(kind, hz).await?;
                    true
                }
            };
            lock(&self.inner.rates).insert(kind, (hz, via_stream));
        }
        Ok(())
    }

    // ------------------------------------------------------------ parameters

    /// The cached value of `name` (from any PARAM_VALUE seen).
    pub fn param_cached(&self, name: &str) -> Option<f32> {
        lock(&self.inner.params).values.get(name).map(|v| v.0)
    }

    /// All cached parameters.
    pub fn params_cached(&self) -> BTreeMap<String, f32> {
        lock(&self.inner.params)
            .values
            .iter()
            .map(|(k, v)| (k.clone(), v.0))
            .collect()
    }

    /// Reads one parameter from the autopilot (and caches it).
    ///
    /// # Errors
    /// No answer after the retries (ArduPilot ignores unknown names).
    pub async fn param_get(&self, name: &str) -> Result<f32, ParamError> {
        if name.len() > 16 {
            return Err(ParamError::NameTooLong(name.to_owned()));
        }
        let target = self.inner.target().await?;
        let _op = self.inner.ops.lock().await;
        let make = |_| {
            MavMessage::PARAM_REQUEST_READ(PARAM_REQUEST_READ_DATA {
                param_index: -1,
                target_system: target.0,
                target_component: target.1,
                param_id: name.into(),
            })
        };
        let matcher = |m: &MavMessage| match m {
            MavMessage::PARAM_VALUE(v) if param_name(&v.param_id) == name => Some(v.param_value),
            _ => None,
        };
        self.inner
            .transact(make, matcher)
            .await?
            .ok_or_else(|| ParamError::RetriesExhausted {
                name: name.to_owned(),
                attempts: self.inner.cfg.retries,
            })
    }

    /// Sets a parameter and checks the autopilot's PARAM_VALUE echoes it.
    ///
    /// # Errors
    /// No answer, or the autopilot reports another value.
    pub async fn param_set(&self, name: &str, value: f32) -> Result<f32, ParamError> {
        if name.len() > 16 {
            return Err(ParamError::NameTooLong(name.to_owned()));
        }
        let target = self.inner.target().await?;
        let _op = self.inner.ops.lock().await;
        let kind = lock(&self.inner.params)
            .values
            .get(name)
            .map_or(MavParamType::MAV_PARAM_TYPE_REAL32, |v| v.1);
        let make = |_| {
            MavMessage::PARAM_SET(PARAM_SET_DATA {
                param_value: value,
                target_system: target.0,
                target_component: target.1,
                param_id: name.into(),
                param_type: kind,
            })
        };
        let matcher = |m: &MavMessage| match m {
            MavMessage::PARAM_VALUE(v) if param_name(&v.param_id) == name => Some(v.param_value),
            _ => None,
        };
        let actual = self.inner.transact(make, matcher).await?.ok_or_else(|| {
            ParamError::RetriesExhausted {
                name: name.to_owned(),
                attempts: self.inner.cfg.retries,
            }
        })?;
        let expected = if kind == MavParamType::MAV_PARAM_TYPE_REAL32 {
            value
        } else {
            value.round()
        };
        if (actual - expected).abs() > 1e-5 * expected.abs().max(1.0) {
            return Err(ParamError::NotApplied {
                name: name.to_owned(),
                requested: value,
                actual,
            });
        }
        Ok(actual)
    }

    /// Reads every parameter: PARAM_REQUEST_LIST, then PARAM_REQUEST_READ for
    /// each index that did not arrive.
    ///
    /// # Errors
    /// Parameters still missing after the retries.
    pub async fn params_list(&self) -> Result<BTreeMap<String, f32>, ParamError> {
        let target = self.inner.target().await?;
        let _op = self.inner.ops.lock().await;
        let mut rx = self.inner.raw_tx.subscribe();
        let mut seen: BTreeMap<u16, (String, f32)> = BTreeMap::new();
        let mut count: Option<u16> = None;
        let collect = |m: &MavMessage| match m {
            MavMessage::PARAM_VALUE(v) => Some((
                v.param_index,
                v.param_count,
                param_name(&v.param_id),
                v.param_value,
            )),
            _ => None,
        };
        for attempt in 0..self.inner.cfg.retries {
            if attempt == 0 || count.is_none() {
                self.inner
                    .send(MavMessage::PARAM_REQUEST_LIST(PARAM_REQUEST_LIST_DATA {
                        target_system: target.0,
                        target_component: target.1,
                    }))
                    .await?;
            } else {
                let missing = (0..count.unwrap_or(0))
                    .filter(|i| !seen.contains_key(i))
                    .collect::<Vec<_>>();
                for index in missing {
                    self.inner
                        .send(MavMessage::PARAM_REQUEST_READ(PARAM_REQUEST_READ_DATA {
                            param_index: index as i16,
                            target_system: target.0,
                            target_component: target.1,
                            param_id: "".into(),
                        }))
                        .await?;
                }
            }
            // Collect until the list is complete or the autopilot goes quiet.
            loop {
                let deadline = Instant::now() + self.inner.cfg.request_timeout;
                match wait_for(&mut rx, deadline, collect).await? {
                    Some((index, total, name, value)) => {
                        count = Some(total);
                        if index < total {
                            seen.insert(index, (name, value));
                        }
                        if seen.len() >= usize::from(total) {
                            return Ok(seen.into_values().collect());
                        }
                    }
                    None => break,
                }
            }
            if count == Some(0) {
                return Ok(BTreeMap::new());
            }
        }
        Err(ParamError::RetriesExhausted {
            name: format!(
                "{} of {:?} parameters",
                count.unwrap_or(0) as usize - seen.len(),
                count
            ),
            attempts: self.inner.cfg.retries,
        })
    }

    // ------------------------------------------------------------ mission

    /// The mission as last uploaded or downloaded through this manager.
    pub fn mission_cached(&self) -> Vec<MissionItem> {
        lock(&self.inner.mission).clone()
    }

    /// Uploads a whole mission. `items[0]` is the home slot on ArduPilot (the
    /// autopilot keeps its own home there). The autopilot stages or overwrites
    /// as it sees fit; on any failure the transfer is cancelled with a
    /// MISSION_ACK so it does not wait for the rest.
    ///
    /// # Errors
    /// Empty list, refusal, or retries exhausted at some item.
    pub async fn mission_upload(&self, items: &[MissionItem]) -> Result<(), MissionError> {
        if items.is_empty() || items.len() > usize::from(u16::MAX) {
            return Err(MissionError::Invalid(format!("{} items", items.len())));
        }
        let target = self.inner.target().await?;
        let _op = self.inner.ops.lock().await;
        let start = MavMessage::MISSION_COUNT(MISSION_COUNT_DATA {
            count: items.len() as u16,
            target_system: target.0,
            target_component: target.1,
        });
        self.inner.upload(target, start, items, 0).await?;
        *lock(&self.inner.mission) = items.to_vec();
        Ok(())
    }

    /// Replaces items `start .. start + items.len()` with MISSION_WRITE_PARTIAL_LIST
    /// (ArduPilot only replaces existing items; it cannot grow the mission).
    ///
    /// # Errors
    /// Empty list, refusal, or retries exhausted (an autopilot that ignores
    /// partial writes fails at [`MissionStage::Start`]).
    pub async fn mission_write_partial(
        &self,
        start: u16,
        items: &[MissionItem],
    ) -> Result<(), MissionError> {
        let end = usize::from(start) + items.len();
        if items.is_empty() || start == 0 || end > i16::MAX as usize {
            return Err(MissionError::Invalid(format!(
                "partial write of {} items at {start}",
                items.len()
            )));
        }
        let target = self.inner.target().await?;
        let _op = self.inner.ops.lock().await;
        let msg = MavMessage::MISSION_WRITE_PARTIAL_LIST(MISSION_WRITE_PARTIAL_LIST_DATA {
            start_index: start as i16,
            end_index: (end - 1) as i16,
            target_system: target.0,
            target_component: target.1,
        });
        self.inner.upload(target, msg, items, start).await?;
        let mut cache = lock(&self.inner.mission);
        if cache.len() >= end {
            cache[usize::from(start)..end].clone_from_slice(items);
        }
        Ok(())
    }

    /// Downloads the whole mission (home first).
    ///
    /// # Errors
    /// Retries exhausted at the count or at some item.
    pub async fn mission_download(&self) -> Result<Vec<MissionItem>, MissionError> {
        let target = self.inner.target().await?;
        let _op = self.inner.ops.lock().await;
        let make = |_| {
            MavMessage::MISSION_REQUEST_LIST(MISSION_REQUEST_LIST_DATA {
                target_system: target.0,
                target_component: target.1,
            })
        };
        let count = self
            .inner
            .transact(make, |m| match m {
                MavMessage::MISSION_COUNT(c) => Some(c.count),
                _ => None,
            })
            .await?
            .ok_or(MissionError::RetriesExhausted {
                stage: MissionStage::Count,
                attempts: self.inner.cfg.retries,
            })?;
        let mut items = Vec::with_capacity(usize::from(count));
        for seq in 0..count {
            let make = |_| {
                MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
                    seq,
                    target_system: target.0,
                    target_component: target.1,
                })
            };
            #[allow(deprecated)] // Legacy autopilots answer with MISSION_ITEM.
            let matcher = |m: &MavMessage| match m {
                MavMessage::MISSION_ITEM_INT(i) if i.seq == seq => Some(MissionItem::from_int(i)),
                MavMessage::MISSION_ITEM(i) if i.seq == seq => Some(MissionItem::from_float(i)),
                _ => None,
            };
            let item = self.inner.transact(make, matcher).await?.ok_or(
                MissionError::RetriesExhausted {
                    stage: MissionStage::Item(seq),
                    attempts: self.inner.cfg.retries,
                },
            )?;
            items.push(item);
        }
        self.inner
            .send(mission_ack(target, MavMissionResult::MAV_MISSION_ACCEPTED))
            .await?;
        *lock(&self.inner.mission) = items.clone();
        Ok(items)
    }

    /// Clears the mission (ArduPilot keeps home). A rover in AUTO still drives
    /// to the item it had memorised, then holds (003 §2.5.4).
    ///
    /// # Errors
    /// Refusal or no answer.
    pub async fn mission_clear(&self) -> Result<(), MissionError> {
        let target = self.inner.target().await?;
        let _op = self.inner.ops.lock().await;
        let make = |_| {
            MavMessage::MISSION_CLEAR_ALL(MISSION_CLEAR_ALL_DATA {
                target_system: target.0,
                target_component: target.1,
            })
        };
        let matcher = |m: &MavMessage| match m {
            MavMessage::MISSION_ACK(a)
                if a.target_system == self.inner.cfg.system_id || a.target_system == 0 =>
            {
                Some(a.mavtype)
            }
            _ => None,
        };
        match self.inner.transact(make, matcher).await? {
            Some(MavMissionResult::MAV_MISSION_ACCEPTED) => {
                lock(&self.inner.mission).clear();
                Ok(())
            }
            Some(other) => Err(MissionError::Rejected(other)),
            None => Err(MissionError::RetriesExhausted {
                stage: MissionStage::Ack,
                attempts: self.inner.cfg.retries,
            }),
        }
    }

    /// Makes `seq` the current item (the vehicle turns to it at once in AUTO),
    /// confirmed by MISSION_CURRENT; falls back to MAV_CMD_DO_SET_MISSION_CURRENT.
    /// The jump is not reported as a waypoint reached.
    ///
    /// # Errors
    /// No confirmation by either method.
    pub async fn mission_set_current(&self, seq: u16) -> Result<(), MissionError> {
        let target = self.inner.target().await?;
        lock(&self.inner.reach).expect_jump(seq);
        #[allow(deprecated)] // MISSION_SET_CURRENT is what ArduPilot of every age understands.
        let make = |_| {
            MavMessage::MISSION_SET_CURRENT(MISSION_SET_CURRENT_DATA {
                seq,
                target_system: target.0,
                target_component: target.1,
            })
        };
        let matcher = |m: &MavMessage| match m {
            MavMessage::MISSION_CURRENT(c) if c.seq == seq => Some(()),
            _ => None,
        };
        // Sent twice per attempt: the rolling queue's wrap has one leg of slack, and setting
        // the same current item twice within milliseconds changes nothing.
        if self
            .inner
            .transact_copies(2, make, matcher)
            .await?
            .is_some()
        {
            return Ok(());
        }
        match self
            .command_long(
                MavCmd::MAV_CMD_DO_SET_MISSION_CURRENT,
                [f32::from(seq), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            )
            .await
        {
            Ok(()) => Ok(()),
            Err(CommandError::Link(e)) => Err(e.into()),
            Err(_) => Err(MissionError::RetriesExhausted {
                stage: MissionStage::SetCurrent,
                attempts: self.inner.cfg.retries * 2,
            }),
        }
    }
}

impl Drop for MavlinkManager {
    fn drop(&mut self) {
        self.cancel.cancel();
    }
}

fn mission_ack(target: (u8, u8), result: MavMissionResult) -> MavMessage {
    MavMessage::MISSION_ACK(MISSION_ACK_DATA {
        target_system: target.0,
        target_component: target.1,
        mavtype: result,
    })
}

/// Waits until `matcher` accepts a message or `deadline` passes (`Ok(None)`).
async fn wait_for<T>(
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

/// What the driver puts on the wire for the requests.
// Messages travel by value as before; boxing them would cost an allocation per message to
// shrink a variant that is sent only before a resend.
#[allow(clippy::large_enum_variant)]
enum Outbound {
    /// A MAVLink message.
    Message(MavMessage),
    /// Filler bytes for a byte-stream link. A MAVLink parser that read a corrupted length
    /// field waits for that many bytes (up to 280) before the CRC tells it the frame is bad
    /// and it rescans; on a quiet uplink that takes seconds, and every resend in between is
    /// swallowed. Zero bytes complete the bogus frame and are skipped while looking for the
    /// next start marker.
    Resync,
}

enum UploadStep {
    Request(u16, bool),
    Ack(MavMissionResult),
}

impl Inner {
    async fn send(&self, msg: MavMessage) -> Result<(), LinkError> {
        self.out_tx
            .send(Outbound::Message(msg))
            .await
            .map_err(|_| LinkError::Closed)
    }

    /// Before a resend: lets a stream receiver stuck on a corrupted length field give up on
    /// it (see [`Outbound::Resync`]).
    async fn resync(&self) -> Result<(), LinkError> {
        self.out_tx
            .send(Outbound::Resync)
            .await
            .map_err(|_| LinkError::Closed)
    }

    /// The autopilot's (system, component), waiting up to `connect_wait` for its first heartbeat.
    async fn target(&self) -> Result<(u8, u8), LinkError> {
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
    async fn transact<T>(
        &self,
        make: impl Fn(u32) -> MavMessage,
        matcher: impl FnMut(&MavMessage) -> Option<T>,
    ) -> Result<Option<T>, LinkError> {
        self.transact_copies(1, make, matcher).await
    }

    /// [`Self::transact`] sending each attempt `copies` times back to back: for idempotent,
    /// time-critical requests, where a duplicate costs a few bytes and a loss a whole timeout.
    async fn transact_copies<T>(
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
    async fn request_stream(&self, kind: Telemetry, hz: f32) -> Result<(), LinkError> {
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

    /// Answers the autopilot's item requests for `items` (numbered from
    /// `first`) after `start` (MISSION_COUNT or MISSION_WRITE_PARTIAL_LIST).
    async fn upload(
        &self,
        target: (u8, u8),
        start: MavMessage,
        items: &[MissionItem],
        first: u16,
    ) -> Result<(), MissionError> {
        let last = first + (items.len() as u16 - 1);
        let mut rx = self.raw_tx.subscribe();
        let me = self.cfg.system_id;
        #[allow(deprecated)] // Legacy autopilots request MISSION_ITEM with MISSION_REQUEST.
        let matcher = |m: &MavMessage| match m {
            MavMessage::MISSION_REQUEST_INT(r) if r.target_system == me => {
                Some(UploadStep::Request(r.seq, true))
            }
            MavMessage::MISSION_REQUEST(r) if r.target_system == me => {
                Some(UploadStep::Request(r.seq, false))
            }
            MavMessage::MISSION_ACK(a) if a.target_system == me || a.target_system == 0 => {
                Some(UploadStep::Ack(a.mavtype))
            }
            _ => None,
        };
        let mut stage = MissionStage::Start;
        let mut attempts = 1;
        let mut last_sent = start.clone();
        self.send(start).await?;
        // Per attempt, not per message received: stale requests and acknowledgements of
        // earlier transfers must not keep postponing the resend.
        let mut deadline = Instant::now() + self.cfg.request_timeout;
        loop {
            match wait_for(&mut rx, deadline, matcher).await? {
                None => {
                    // Silence: our last message or the autopilot's request was lost.
                    if attempts >= self.cfg.retries {
                        self.send(mission_ack(
                            target,
                            MavMissionResult::MAV_MISSION_OPERATION_CANCELLED,
                        ))
                        .await?;
                        return Err(MissionError::RetriesExhausted { stage, attempts });
                    }
                    attempts += 1;
                    tracing::debug!("mission transfer: silence at {stage:?}, attempt {attempts}");
                    self.resync().await?;
                    self.send(last_sent.clone()).await?;
                    deadline = Instant::now() + self.cfg.request_timeout;
                }
                Some(UploadStep::Request(seq, int)) => {
                    if seq < first || seq > last {
                        // A stale request from an earlier transfer.
                        continue;
                    }
                    if stage == MissionStage::Item(seq) {
                        attempts += 1;
                        if attempts > self.cfg.retries {
                            self.send(mission_ack(
                                target,
                                MavMissionResult::MAV_MISSION_OPERATION_CANCELLED,
                            ))
                            .await?;
                            return Err(MissionError::RetriesExhausted { stage, attempts });
                        }
                    } else {
                        stage = MissionStage::Item(seq);
                        attempts = 1;
                    }
                    let item = &items[usize::from(seq - first)];
                    #[allow(deprecated)]
                    let msg = if int {
                        MavMessage::MISSION_ITEM_INT(item.to_int(seq, target))
                    } else {
                        MavMessage::MISSION_ITEM(item.to_float(seq, target))
                    };
                    last_sent = msg.clone();
                    self.send(msg).await?;
                    deadline = Instant::now() + self.cfg.request_timeout;
                }
                Some(UploadStep::Ack(MavMissionResult::MAV_MISSION_ACCEPTED)) => {
                    if stage == MissionStage::Item(last) {
                        return Ok(());
                    }
                    // An ACK for an earlier transfer: ignore.
                }
                Some(UploadStep::Ack(result)) => return Err(MissionError::Rejected(result)),
            }
        }
    }

    fn emit(&self, e: MavEvent) {
        let _ = self.events_tx.send(e);
    }

    fn reached(&self, seq: Option<u16>, source: ReachSource) {
        if let Some(seq) = seq {
            self.emit(MavEvent::WaypointReached { seq, source });
        }
    }

    fn link_lost(&self) {
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
    fn on_frame(&self, frame: Frame, last_hb: &mut Option<Instant>) -> bool {
        let Frame { header, msg, .. } = frame;
        let (sys, comp) = (header.system_id as u8, header.component_id);
        let known = self.state_tx.borrow().system_id;
        let mut came_up = false;
        if let MavMessage::HEARTBEAT(hb) = &msg {
            let is_autopilot = hb.autopilot != MavAutopilot::MAV_AUTOPILOT_INVALID
                && hb.mavtype != MavType::MAV_TYPE_GCS;
            if is_autopilot && (known.is_none() || known == Some(sys)) {
                *last_hb = Some(Instant::now());
                came_up = self.on_heartbeat(sys, comp, hb);
            }
        }
        if known.is_some_and(|k| k != sys) || (known.is_none() && !came_up) {
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

    fn on_heartbeat(&self, sys: u8, comp: u8, hb: &HEARTBEAT_DATA) -> bool {
        let armed = hb
            .base_mode
            .contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED);
        let name = modes::name(hb.mavtype, hb.custom_mode);
        let before = self.state_tx.borrow().clone();
        self.state_tx.send_modify(|s| {
            s.link_up = true;
            s.system_id = Some(sys);
            s.component_id = Some(comp);
            s.vehicle_type = Some(hb.mavtype);
            s.mode = Some(hb.custom_mode);
            s.mode_name = name;
            s.armed = armed;
            s.system_status = Some(hb.system_status);
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
    fn rate_messages(&self, target: (u8, u8)) -> Vec<MavMessage> {
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

async fn driver(
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
