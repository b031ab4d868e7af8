//! [`MavlinkManager`]: one async handle on one autopilot (003 §3.2.2): its configuration,
//! state, events and commands.
//!
//! A driver task ([`super::driver`]) owns the connection and keeps the [`VehicleState`] up to
//! date. Requests (commands here, [`super::param`] and [`super::mission`] transfers) run in the
//! caller's task: they subscribe to the raw message stream, send through the driver and wait
//! with a per-attempt timeout and a bounded number of retries. Mission and parameter
//! transactions are serialised so two callers cannot interleave on the wire.

use std::sync::{Arc, Mutex as StdMutex};
use std::time::Duration;

use marea::sync::lock;
use mavconn::Endpoint;
use mavlink::dialects::ardupilotmega::{
    MavAutopilot, MavCmd, MavDataStream, MavFrame, MavMessage, MavModeFlag, MavResult, MavState,
    MavType, COMMAND_INT_DATA, COMMAND_LONG_DATA, RC_CHANNELS_OVERRIDE_DATA,
};
use tokio::sync::{broadcast, mpsc, watch};
use tokio::task::JoinHandle;
use tokio::time::timeout;
use tokio_util::sync::CancellationToken;

use super::driver::{driver, Inner};
use super::family::AutopilotFamily;
use super::forward::forwarder;
use super::modes::{self, ModeSpec};
use super::types::*;

/// How many times a command answered MAV_RESULT_TEMPORARILY_REJECTED is asked in all.
const TEMPORARY_ASKS: u32 = 4;
/// The wait before asking again a command answered TEMPORARILY_REJECTED, doubled each time
/// (0.25 + 0.5 + 1 s: under two seconds before the refusal is final).
const TEMPORARY_RETRY_START: Duration = Duration::from_millis(250);

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
    /// MAVLink 2 signing toward the autopilot: sign everything, accept only correctly signed
    /// frames.
    pub signing: Option<mavconn::Signing>,
    /// Pin the autopilot (system, component, UDP address) at its first heartbeat.
    pub pin: Option<mavconn::Pin>,
    /// The autopilot family; `None`: from the heartbeat's `autopilot` field.
    pub family: Option<AutopilotFamily>,
    /// The autopilot's system id, where several vehicles share one link; `None`: the first
    /// autopilot heard.
    pub target_system: Option<u8>,
    /// The autopilot's component id, where several components of a vehicle share the link
    /// (MAV_COMP_ID_AUTOPILOT1 is 1); `None`: the first autopilot component heard. Traffic of
    /// every other component is ignored (and forwarded).
    pub target_component: Option<u8>,
    /// Extra endpoints MAVLink is forwarded to and from (another ground station), as
    /// `udpout:HOST:PORT` and the like.
    pub forward: Vec<String>,
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
            signing: None,
            pin: None,
            family: None,
            target_system: None,
            target_component: None,
            forward: Vec::new(),
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
    /// The heartbeat's autopilot field, once seen.
    pub autopilot: Option<MavAutopilot>,
    /// The family whose conventions apply (configured, or from `autopilot`).
    pub family: AutopilotFamily,
    /// Custom modes are PX4's `main << 16 | sub << 24` (the PX4 family, or a generic
    /// autopilot whose heartbeat shows that encoding, as MAVSDK's server does).
    pub px4_modes: bool,
    /// Custom mode (ArduPilot number, or PX4's `main << 16 | sub << 24`).
    pub mode: Option<u32>,
    /// Its ArduPilot name.
    pub mode_name: Option<&'static str>,
    /// Armed flag.
    pub armed: bool,
    /// MAV_STATE (the thesis' "AutopilotState").
    pub system_status: Option<MavState>,
    /// Last MISSION_CURRENT.
    pub mission_current: Option<u16>,
    /// AUTOPILOT_VERSION's capability bits (MAV_PROTOCOL_CAPABILITY), once reported.
    pub capabilities: Option<u64>,
    /// How many times heartbeats came back after being lost (each time a
    /// [`MavEvent::LinkRestored`](super::MavEvent::LinkRestored) follows): a reader of this
    /// state can tell that a restoration it has not handled yet is already reflected here.
    pub restorations: u32,
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
    pub(crate) fn message_id(self) -> u32 {
        match self {
            Self::Position => 33,
            Self::Attitude => 30,
            Self::VfrHud => 74,
            Self::SysStatus => 1,
            Self::MissionCurrent => 42,
        }
    }

    #[allow(deprecated)] // REQUEST_DATA_STREAM is the fallback for autopilots without SET_MESSAGE_INTERVAL.
    pub(crate) fn stream(self) -> MavDataStream {
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

/// The MAVLink communication manager: one autopilot, any transport.
pub struct MavlinkManager {
    pub(super) inner: Arc<Inner>,
    cancel: CancellationToken,
    driver: Option<JoinHandle<()>>,
    forwarders: Vec<JoinHandle<()>>,
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
        let forwards = cfg
            .forward
            .iter()
            .map(|f| f.parse::<Endpoint>())
            .collect::<Result<Vec<_>, _>>()?;
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
            partial: StdMutex::default(),
            frames_tx: broadcast::channel(1024).0,
        });
        let cancel = CancellationToken::new();
        let driver = tokio::spawn(driver(inner.clone(), endpoint, out_rx, cancel.clone()));
        let forwarders = forwards
            .into_iter()
            .map(|f| tokio::spawn(forwarder(inner.clone(), f, cancel.clone())))
            .collect();
        Ok(Self {
            inner,
            cancel,
            driver: Some(driver),
            forwarders,
        })
    }

    /// Stops the driver and closes the transport.
    pub async fn shutdown(mut self) {
        self.cancel.cancel();
        if let Some(driver) = self.driver.take() {
            let _ = driver.await;
        }
        for f in self.forwarders.drain(..) {
            let _ = f.await;
        }
    }

    /// Every event from now on. A slow receiver loses the oldest events (`Lagged`).
    pub fn subscribe(&self) -> broadcast::Receiver<MavEvent> {
        self.inner.events_tx.subscribe()
    }

    /// Asks for HOME_POSITION (MAV_CMD_REQUEST_MESSAGE); the answer arrives as
    /// [`MavEvent::Home`].
    ///
    /// # Errors
    /// Not connected, or the autopilot refused or did not answer the request.
    pub async fn request_home(&self) -> Result<(), CommandError> {
        self.command_long(
            MavCmd::MAV_CMD_REQUEST_MESSAGE,
            [242.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        )
        .await
    }

    /// Asks for AUTOPILOT_VERSION (MAV_CMD_REQUEST_MESSAGE, else the older
    /// MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES) and waits up to one request timeout for its
    /// capabilities ([`VehicleState::capabilities`]).
    ///
    /// # Errors
    /// Not connected; `Ok(None)` when the autopilot does not tell.
    pub async fn request_capabilities(&self) -> Result<Option<u64>, LinkError> {
        if let Some(c) = self.state().capabilities {
            return Ok(Some(c));
        }
        let mut rx = self.inner.state_tx.subscribe();
        let asked = match self
            .command_long(
                MavCmd::MAV_CMD_REQUEST_MESSAGE,
                [148.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            )
            .await
        {
            Err(CommandError::Link(e)) => return Err(e),
            Ok(()) => true,
            Err(_) => false,
        };
        if !asked {
            match self
                .command_long(
                    MavCmd::MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
                    [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
                )
                .await
            {
                Err(CommandError::Link(e)) => return Err(e),
                Ok(()) => {}
                // Neither request understood: it will not tell (unless it already did).
                Err(_) => return Ok(self.state().capabilities),
            }
        }
        let got = timeout(
            self.inner.cfg.request_timeout,
            rx.wait_for(|s| s.capabilities.is_some()),
        )
        .await;
        Ok(match got {
            Ok(Ok(s)) => s.capabilities,
            _ => None,
        })
    }

    /// How long the manager waits for a heartbeat to confirm a change (and declares the link
    /// lost without one).
    pub fn heartbeat_timeout(&self) -> Duration {
        self.inner.cfg.heartbeat_timeout
    }

    /// The autopilot family whose conventions apply (configured, or from the heartbeat).
    pub fn family(&self) -> AutopilotFamily {
        self.inner.state_tx.borrow().family
    }

    /// Whether the autopilot answers MISSION_WRITE_PARTIAL_LIST on this connection: `None`
    /// until the first partial write probed it.
    pub fn partial_writes(&self) -> Option<bool> {
        *lock(&self.inner.partial)
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

    /// The link's counters, summed over reopenings: parse errors, drops, frames refused by
    /// signing and by pinning.
    pub fn counters(&self) -> &mavconn::Counters {
        &self.inner.counters
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
        self.acknowledged(command, make).await
    }

    /// Sends COMMAND_INT (a command with a position: `x`, `y` in 1e-7 degrees for a global
    /// `frame`, `z` in metres) and checks its COMMAND_ACK, retrying on silence. `params` are
    /// param1 to param4.
    ///
    /// # Errors
    /// No ACK after the retries, or an ACK other than ACCEPTED.
    pub async fn command_int(
        &self,
        command: MavCmd,
        frame: MavFrame,
        params: [f32; 4],
        (x, y, z): (i32, i32, f32),
    ) -> Result<(), CommandError> {
        let target = self.inner.target().await?;
        let make = |_attempt: u32| {
            MavMessage::COMMAND_INT(COMMAND_INT_DATA {
                param1: params[0],
                param2: params[1],
                param3: params[2],
                param4: params[3],
                x,
                y,
                z,
                command,
                target_system: target.0,
                target_component: target.1,
                frame,
                current: 0,
                autocontinue: 0,
            })
        };
        self.acknowledged(command, make).await
    }

    /// Sends the command message `make` builds (per attempt) and checks the COMMAND_ACK for
    /// `command`, retrying on silence.
    async fn acknowledged(
        &self,
        command: MavCmd,
        make: impl Fn(u32) -> MavMessage,
    ) -> Result<(), CommandError> {
        let matcher = |m: &MavMessage| match m {
            MavMessage::COMMAND_ACK(a) if a.command == command => Some(a.result),
            _ => None,
        };
        // "Not now" (an autopilot whose own checks are still running) is asked again, a
        // little later each time; any other answer is final.
        let mut wait = TEMPORARY_RETRY_START;
        for asked in 1.. {
            match self.inner.transact(&make, matcher).await? {
                Some(MavResult::MAV_RESULT_ACCEPTED) => return Ok(()),
                Some(MavResult::MAV_RESULT_TEMPORARILY_REJECTED) if asked < TEMPORARY_ASKS => {
                    tracing::debug!("{command:?} temporarily rejected; asking again in {wait:?}");
                    tokio::time::sleep(wait).await;
                    wait *= 2;
                }
                Some(result) => return Err(CommandError::Rejected { command, result }),
                None => {
                    return Err(CommandError::RetriesExhausted {
                        command,
                        attempts: self.inner.cfg.retries,
                    })
                }
            }
        }
        unreachable!("the loop returns")
    }

    /// MAV_CMD_DO_REPOSITION (as COMMAND_INT): the vehicle goes to (`lat`, `lon`) (NaN: where
    /// it is) at `speed` m/s (≤ 0: its default) and holds there, switching to its hold mode
    /// (PX4's AUTO.LOITER) first. `alt` is metres above home (NaN: keep).
    ///
    /// # Errors
    /// Refusal or no answer.
    pub async fn reposition(
        &self,
        lat: f64,
        lon: f64,
        alt: f32,
        speed: f32,
    ) -> Result<(), CommandError> {
        let deg = |d: f64| {
            if d.is_finite() {
                (d * 1e7)
                    .round()
                    .clamp(f64::from(i32::MIN), f64::from(i32::MAX)) as i32
            } else {
                // "Unchanged" for PX4: its own position.
                i32::MAX
            }
        };
        // param2 bit 0: MAV_DO_REPOSITION_FLAGS_CHANGE_MODE; param4 NaN: keep the heading.
        let speed = if speed.is_finite() && speed > 0.0 {
            speed
        } else {
            -1.0
        };
        self.command_int(
            MavCmd::MAV_CMD_DO_REPOSITION,
            MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
            [speed, 1.0, 0.0, f32::NAN],
            (deg(lat), deg(lon), alt),
        )
        .await
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
        let px4 = self.state().px4_modes;
        let number = match mode.into() {
            ModeSpec::Number(n) => n,
            ModeSpec::Name(name) if px4 => {
                modes::px4_number(&name).ok_or(CommandError::UnknownMode(name))?
            }
            ModeSpec::Name(name) => {
                let vehicle = self
                    .state()
                    .vehicle_type
                    .unwrap_or(MavType::MAV_TYPE_GENERIC);
                modes::number(vehicle, &name).ok_or(CommandError::UnknownMode(name))?
            }
        };
        if self.state().mode == Some(number) {
            // Already there: nothing to ask (some autopilots, MAVSDK's server among them,
            // refuse a change to a mode they only enter by themselves, such as HOLD).
            return Ok(());
        }
        let custom = f32::from(MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED.bits());
        // PX4 takes the main and sub mode in param2 and param3; ArduPilot the number in param2.
        let (p2, p3) = if px4 {
            let (main, sub) = modes::px4_main_sub(number);
            (f32::from(main), f32::from(sub))
        } else {
            (number as f32, 0.0)
        };
        self.command_long(
            MavCmd::MAV_CMD_DO_SET_MODE,
            [custom, p2, p3, 0.0, 0.0, 0.0, 0.0],
        )
        .await?;
        self.confirm(format!("mode {number}"), |s| s.mode == Some(number))
            .await
    }

    /// Starts the mission with MAV_CMD_MISSION_START from item `first` (PX4's way into
    /// AUTO.MISSION where a mode change is refused), waiting for a heartbeat in AUTO.
    ///
    /// # Errors
    /// Refusal, no answer, or no confirming heartbeat.
    pub async fn mission_start(&self, first: u16) -> Result<(), CommandError> {
        self.command_long(
            MavCmd::MAV_CMD_MISSION_START,
            [f32::from(first), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        )
        .await?;
        self.confirm("mode AUTO".to_owned(), |s| s.mode_name == Some("AUTO"))
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
                    ..Default::default()
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
}

impl Drop for MavlinkManager {
    fn drop(&mut self) {
        self.cancel.cancel();
    }
}
