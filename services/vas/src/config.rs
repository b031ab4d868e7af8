//! The VAS configuration: an XML file (`<vas .../>`, see `vas.example.xml`), overridden by
//! command-line flags.

use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::Deserialize;
use usal_types::{Fence, VehicleKind};

use crate::apl::mavlink::MavlinkApConfig;
use crate::mavlink_cm::{AutopilotFamily, ManagerConfig};
use crate::val::ValConfig;

/// The autopilot families the VAS has an APL for.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AutopilotKind {
    /// The family the autopilot's heartbeat names (its `autopilot` field).
    #[default]
    Auto,
    /// ArduPilot (Rover, Copter, Plane) and mavsim, over MAVLink.
    Ardupilot,
    /// PX4: PX4 custom modes, item 0 ordinary, uploads reset the current item.
    Px4,
    /// Another MAVLink autopilot (MAVSDK's server...): item 0 ordinary, the current item
    /// restored after every upload.
    Generic,
}

impl AutopilotKind {
    /// The family the configuration names, `None` for the heartbeat's.
    pub fn family(self) -> Option<AutopilotFamily> {
        match self {
            Self::Auto => None,
            Self::Ardupilot => Some(AutopilotFamily::ArduPilot),
            Self::Px4 => Some(AutopilotFamily::Px4),
            Self::Generic => Some(AutopilotFamily::Generic),
        }
    }

    /// The name in the configuration.
    pub fn name(self) -> &'static str {
        match self {
            Self::Auto => "auto",
            Self::Ardupilot => "ardupilot",
            Self::Px4 => "px4",
            Self::Generic => "generic",
        }
    }
}

impl std::str::FromStr for AutopilotKind {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        [Self::Auto, Self::Ardupilot, Self::Px4, Self::Generic]
            .into_iter()
            .find(|k| k.name() == s)
            .ok_or_else(|| {
                format!("`{s}` is not an autopilot family (auto, ardupilot, px4, generic)")
            })
    }
}

/// Everything `vas` needs to run. Attribute names of the XML file in brackets.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VasConfig {
    /// Autopilot family (`autopilot`).
    #[serde(rename = "@autopilot")]
    pub autopilot: AutopilotKind,
    /// MAVLink endpoint (`endpoint`): `udpout:HOST:PORT`, `udpin:ADDR:PORT`,
    /// `tcpout:HOST:PORT`, `serial:PATH:BAUD`.
    #[serde(rename = "@endpoint")]
    pub endpoint: String,
    /// Vehicle kind (`vehicle`): rover, copter, plane.
    #[serde(rename = "@vehicle")]
    pub vehicle: VehicleKind,
    /// Rolling-queue slots on the autopilot (`queueSize`), ≥ 3.
    #[serde(rename = "@queueSize")]
    pub queue_size: u16,
    /// Position/attitude/speed telemetry rate in Hz (`telemetryHz`).
    #[serde(rename = "@telemetryHz")]
    pub telemetry_hz: f32,
    /// Status and mission-progress rate in Hz (`statusHz`).
    #[serde(rename = "@statusHz")]
    pub status_hz: f32,
    /// Autopilot heartbeat timeout before the link is declared lost, ms (`heartbeatTimeoutMs`).
    #[serde(rename = "@heartbeatTimeoutMs")]
    pub heartbeat_timeout_ms: u64,
    /// How long one attempt of a MAVLink request (a command, one mission item) waits for its
    /// answer, ms (`requestTimeoutMs`). A few round trips of the link: lower it on a fast lossy
    /// radio so a lost frame costs little, raise it on a slow one.
    #[serde(rename = "@requestTimeoutMs")]
    pub request_timeout_ms: u64,
    /// Attempts per MAVLink request and per mission item before the transfer is cancelled
    /// (`retries`).
    #[serde(rename = "@retries")]
    pub retries: u32,
    /// The middleware's network.xml (`network`); none: Ethernet on loopback.
    #[serde(rename = "@network")]
    pub network: Option<PathBuf>,
    /// Overrides the network file's domain (`domain`).
    #[serde(rename = "@domain")]
    pub domain: Option<String>,
    /// Overrides the network file's namespace (`namespace`), e.g. `rover1`.
    #[serde(rename = "@namespace")]
    pub namespace: Option<String>,
    /// Pattern of the FMo's manual-control variable (`manualControl`).
    #[serde(rename = "@manualControl")]
    pub manual_control: String,
    /// Manual-control staleness timeout, ms (`manualTimeoutMs`).
    #[serde(rename = "@manualTimeoutMs")]
    pub manual_timeout_ms: u64,
    /// The stations whose manual control is obeyed (`manualStations`), comma-separated: each a
    /// publishing node's name or a prefix of the sample's item name (`ground-fmo`,
    /// `ground/fmo`). Unset: any station (the launcher sets the mission's FMo stations).
    #[serde(rename = "@manualStations")]
    pub manual_stations: Option<String>,
    /// Manual-control samples stamped further ahead of our clock are refused, ms
    /// (`manualSkewMs`).
    #[serde(rename = "@manualSkewMs")]
    pub manual_skew_ms: u64,
    /// Largest |altitude| above home a pushed waypoint may have, metres (`maxAltitudeM`).
    #[serde(rename = "@maxAltitudeM")]
    pub max_altitude_m: f64,
    /// Most waypoints in one `push_waypoints` call (`maxWaypointsPerCall`).
    #[serde(rename = "@maxWaypointsPerCall")]
    pub max_waypoints_per_call: usize,
    /// Most waypoints queued at once (`maxQueuedWaypoints`).
    #[serde(rename = "@maxQueuedWaypoints")]
    pub max_queued_waypoints: u64,
    /// The vehicle's own fence (`<fence maxDistance homeLat homeLon maxHeight action><pt lat
    /// lon/>...</fence>`, the plan's `<fence>` form): uploaded to the autopilot before the
    /// vehicle may start, and kept for the whole flight; a plan's fence may only narrow it.
    #[serde(rename = "fence")]
    pub fence: Option<FenceSettings>,
    /// The directory of the air-side log (`airLog`; see `airlog`): states, commands received
    /// with who sent them and the answers, mission traffic, failsafes and alarms. None: no log.
    #[serde(rename = "@airLog")]
    pub air_log: Option<PathBuf>,
    /// The air log's bound per file, MiB (`airLogMaxMb`, default 8; two files are kept).
    #[serde(rename = "@airLogMaxMb")]
    pub air_log_max_mb: u64,
    /// A parameter file (`params`, Mission Planner's or QGroundControl's format) set on the
    /// autopilot at start-up, each value verified; refusals are alarms.
    #[serde(rename = "@params")]
    pub params: Option<PathBuf>,
    /// MAVLink 2 signing toward the autopilot (`<signing keyFile=".." linkId="1"/>`).
    #[serde(rename = "signing")]
    pub signing: Option<SigningSettings>,
    /// Pin the autopilot at its first heartbeat (`pinAutopilot`, default true): afterwards
    /// frames from another system, component or UDP address are dropped and counted.
    #[serde(rename = "@pinAutopilot")]
    pub pin_autopilot: bool,
    /// The autopilot's system id to pin (`autopilotSysid`); none: the first heartbeat's.
    #[serde(rename = "@autopilotSysid")]
    pub autopilot_sysid: Option<u8>,
    /// The autopilot's UDP address (`autopilotPeer="ip:port"`): a `udpin` endpoint answers it
    /// from the start and listens to nobody else.
    #[serde(rename = "@autopilotPeer")]
    pub autopilot_peer: Option<std::net::SocketAddr>,
    /// Extra endpoints MAVLink is forwarded to and from, like mavlink-router
    /// (`<forward endpoint="udpout:127.0.0.1:14550"/>` child elements): another ground station
    /// watches, and can take over, the vehicle.
    #[serde(rename = "forward")]
    pub forward: Vec<ForwardConfig>,
    /// The autopilot's MAVLink system id where several vehicles share one link
    /// (`targetSystem`); none: the first autopilot heard.
    #[serde(rename = "@targetSystem")]
    pub target_system: Option<u8>,
    /// Silence of the ground station (its heartbeat, or the radio reaching no peer) after
    /// which the ground link is lost, ms (`linkLossTimeoutMs`, default 5000).
    #[serde(rename = "@linkLossTimeoutMs")]
    pub link_loss_timeout_ms: u64,
    /// What the VAS does then (`linkLossAction`): `continue` (alarm only, the default),
    /// `hold`, `rtl`.
    #[serde(rename = "@linkLossAction")]
    pub link_loss_action: String,
    /// What the VAS does when the link returns (`linkRecovery`): `wait` for the operator
    /// (default) or `resume` the state the loss interrupted.
    #[serde(rename = "@linkRecovery")]
    pub link_recovery: String,
    /// Pattern of the station heartbeat variable followed (`stationHeartbeat`, default
    /// `**/heartbeat`).
    #[serde(rename = "@stationHeartbeat")]
    pub station_heartbeat: String,
    /// The radio link whose health is followed (`radioLink`, default `radio`; empty: none):
    /// `<namespace>/link/<radioLink>/stats`.
    #[serde(rename = "@radioLink")]
    pub radio_link: String,
    /// After an autopilot reboot (it comes back in another mode than commanded), put it
    /// back in the commanded state, re-arming it, and raise an alarm saying so
    /// (`resumeAfterReboot`, default false: the VAS follows the state the autopilot reports
    /// and an alarm asks the operator to restart).
    #[serde(rename = "@resumeAfterReboot")]
    pub resume_after_reboot: bool,
    /// The autopilot's MAVLink component id where several components of the vehicle share
    /// the link (`targetComponent`, 1 for MAV_COMP_ID_AUTOPILOT1); none: the first autopilot
    /// component heard. Other components' traffic is ignored (and forwarded).
    #[serde(rename = "@targetComponent")]
    pub target_component: Option<u8>,
}

/// The `<fence>` element: the vehicle's fence, written as a plan writes its own.
#[derive(Clone, Debug, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FenceSettings {
    /// Largest distance from home, metres (`maxDistance`; needs `homeLat`/`homeLon`).
    #[serde(rename = "@maxDistance")]
    pub max_distance: Option<f64>,
    /// Largest height above home, metres (`maxHeight`).
    #[serde(rename = "@maxHeight")]
    pub max_height: Option<f64>,
    /// Home's latitude (`homeLat`).
    #[serde(rename = "@homeLat")]
    pub home_lat: Option<f64>,
    /// Home's longitude (`homeLon`).
    #[serde(rename = "@homeLon")]
    pub home_lon: Option<f64>,
    /// `report`, `rtl` (default) or `hold` (`action`).
    #[serde(rename = "@action")]
    pub action: Option<String>,
    /// The inclusion polygon (`<pt lat lon/>` children).
    #[serde(rename = "pt", default)]
    pub pt: Vec<FencePoint>,
}

/// One `<pt lat lon/>` of a `<fence>`.
#[derive(Clone, Debug, Default, PartialEq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FencePoint {
    /// Latitude, degrees.
    #[serde(rename = "@lat")]
    pub lat: f64,
    /// Longitude, degrees.
    #[serde(rename = "@lon")]
    pub lon: f64,
}

impl FenceSettings {
    /// Reads a file whose root is `<fence>` (`vas --fence`, what `usal run` writes).
    ///
    /// # Errors
    /// Unreadable file, malformed XML, or a fence that is not one.
    pub fn load(path: &Path) -> Result<Self, ConfigLoadError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigLoadError::Read {
            path: path.to_owned(),
            source,
        })?;
        let f: Self = marea::xml::de::from_document(&text).map_err(|e| ConfigLoadError::Parse {
            path: path.to_owned(),
            source: Box::new(e),
        })?;
        f.fence()
            .map_err(|e| ConfigLoadError::Invalid(format!("{}: {e}", path.display())))?;
        Ok(f)
    }

    /// The fence it describes.
    ///
    /// # Errors
    /// What is wrong, e.g. `<fence>: maxDistance needs homeLat and homeLon`.
    pub fn fence(&self) -> Result<Fence, String> {
        let home = match (self.home_lat, self.home_lon) {
            (Some(lat), Some(lon)) => Some((lat, lon)),
            (None, None) => None,
            _ => return Err("<fence>: give both homeLat and homeLon, or neither".into()),
        };
        if self.max_distance.is_some() && home.is_none() {
            return Err(
                "<fence>: maxDistance needs homeLat and homeLon (where it is measured from)".into(),
            );
        }
        let action = match &self.action {
            None => usal_types::FenceAction::default(),
            Some(a) => a.parse().map_err(|e| format!("<fence action>: {e}"))?,
        };
        let fence = Fence {
            home: home.unwrap_or_default(),
            max_distance_m: self.max_distance,
            max_height_m: self.max_height,
            polygon: self.pt.iter().map(|p| (p.lat, p.lon)).collect(),
            action,
        };
        if fence.is_empty() {
            return Err("<fence>: set maxDistance, maxHeight or at least 3 <pt> vertices".into());
        }
        fence.validate().map_err(|e| format!("<fence>: {e}"))?;
        Ok(fence)
    }
}

/// The `<signing keyFile=".." linkId="1"/>` element of the VAS configuration.
#[derive(Clone, Debug, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SigningSettings {
    /// The 32-byte secret as 64 hex digits; refused if group/world-readable (`keyFile`).
    #[serde(rename = "@keyFile")]
    pub key_file: PathBuf,
    /// Link id put in our signatures (`linkId`, default 0).
    #[serde(rename = "@linkId", default)]
    pub link_id: u8,
}

/// One `<forward endpoint="..."/>` element.
#[derive(Clone, Debug, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ForwardConfig {
    /// `udpout:HOST:PORT`, `udpin:ADDR:PORT`, `tcpout:HOST:PORT`, `serial:PATH:BAUD`.
    #[serde(rename = "@endpoint")]
    pub endpoint: String,
}

impl Default for VasConfig {
    fn default() -> Self {
        let val = ValConfig::default();
        let manager = ManagerConfig::default();
        Self {
            autopilot: AutopilotKind::Auto,
            endpoint: "udpout:127.0.0.1:14560".into(),
            vehicle: VehicleKind::Rover,
            queue_size: 5,
            telemetry_hz: 4.0,
            status_hz: 1.0,
            heartbeat_timeout_ms: 3000,
            request_timeout_ms: manager.request_timeout.as_millis() as u64,
            retries: manager.retries,
            network: None,
            domain: None,
            namespace: None,
            manual_control: val.manual_control,
            manual_timeout_ms: val.manual_timeout.as_millis() as u64,
            manual_stations: None,
            manual_skew_ms: val.manual_skew.as_millis() as u64,
            max_altitude_m: val.waypoints.max_alt_m,
            max_waypoints_per_call: val.waypoints.max_per_call,
            max_queued_waypoints: val.waypoints.max_queued,
            fence: None,
            params: None,
            air_log: None,
            air_log_max_mb: 8,
            signing: None,
            pin_autopilot: true,
            autopilot_sysid: None,
            autopilot_peer: None,
            target_system: None,
            target_component: None,
            forward: Vec::new(),
            link_loss_timeout_ms: val.link_loss.timeout.as_millis() as u64,
            link_loss_action: val.link_loss.action.name().into(),
            link_recovery: val.link_loss.recovery.name().into(),
            station_heartbeat: val.link_loss.heartbeat.clone(),
            radio_link: val.link_loss.radio_link.clone().unwrap_or_default(),
            resume_after_reboot: false,
        }
    }
}

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
    /// The XML is malformed or has unknown or ill-typed attributes.
    #[error("{}:{source}", path.display())]
    Parse {
        /// The file.
        path: PathBuf,
        /// What was refused, and where.
        source: Box<marea::xml::de::XmlDeError>,
    },
    /// A value is out of range.
    #[error("{0}")]
    Invalid(String),
    /// The signing key file cannot be used.
    #[error(transparent)]
    SigningKey(#[from] mavconn::SigningKeyLoadError),
}

impl VasConfig {
    /// Reads a `<vas .../>` file.
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
        for f in &self.forward {
            if let Err(e) = f.endpoint.parse::<crate::mavlink_cm::Endpoint>() {
                return Err(ConfigLoadError::Invalid(format!(
                    "<forward endpoint=\"{}\">: {e}",
                    f.endpoint
                )));
            }
        }
        if self.queue_size < 3 {
            return Err(ConfigLoadError::Invalid(format!(
                "queueSize {} < 3: the rolling queue needs two slots plus the mirror slot",
                self.queue_size
            )));
        }
        for (name, hz) in [
            ("telemetryHz", self.telemetry_hz),
            ("statusHz", self.status_hz),
        ] {
            if !(hz.is_finite() && hz > 0.0 && hz <= 50.0) {
                return Err(ConfigLoadError::Invalid(format!(
                    "{name} {hz} not in (0, 50]"
                )));
            }
        }
        if self.heartbeat_timeout_ms < 500 {
            return Err(ConfigLoadError::Invalid(
                "heartbeatTimeoutMs below 500".into(),
            ));
        }
        if !(10..=60_000).contains(&self.request_timeout_ms) {
            return Err(ConfigLoadError::Invalid(format!(
                "requestTimeoutMs {} not in [10, 60000]",
                self.request_timeout_ms
            )));
        }
        if !(1..=100).contains(&self.retries) {
            return Err(ConfigLoadError::Invalid(format!(
                "retries {} not in [1, 100]",
                self.retries
            )));
        }
        if !(self.max_altitude_m.is_finite() && self.max_altitude_m > 0.0) {
            return Err(ConfigLoadError::Invalid(format!(
                "maxAltitudeM {} is not a positive number",
                self.max_altitude_m
            )));
        }
        if !(100..=3_600_000).contains(&self.link_loss_timeout_ms) {
            return Err(ConfigLoadError::Invalid(format!(
                "linkLossTimeoutMs {} not in [100, 3600000]",
                self.link_loss_timeout_ms
            )));
        }
        self.link_loss()?;
        if !(1..=4096).contains(&self.air_log_max_mb) {
            return Err(ConfigLoadError::Invalid(format!(
                "airLogMaxMb {} not in [1, 4096]",
                self.air_log_max_mb
            )));
        }
        if let Some(f) = &self.fence {
            f.fence().map_err(ConfigLoadError::Invalid)?;
        }
        if self.max_waypoints_per_call == 0 || self.max_queued_waypoints == 0 {
            return Err(ConfigLoadError::Invalid(
                "maxWaypointsPerCall and maxQueuedWaypoints must be at least 1".into(),
            ));
        }
        Ok(())
    }

    /// The MAVLink signing the configuration asks for, its key read from its file.
    ///
    /// # Errors
    /// The key file is unreadable, malformed or readable by group/world.
    pub fn signing(&self) -> Result<Option<mavconn::Signing>, ConfigLoadError> {
        let Some(s) = &self.signing else {
            return Ok(None);
        };
        Ok(Some(mavconn::Signing {
            key: mavconn::SigningKey::load(&s.key_file)?,
            link_id: s.link_id,
        }))
    }

    /// How the autopilot is pinned (`None` with `pinAutopilot="false"`).
    pub fn pin(&self) -> Option<mavconn::Pin> {
        // Released once the link is declared lost anyway, so a restarted autopilot is
        // followed; a spoofer must first silence the real one for that long.
        self.pin_autopilot.then_some(mavconn::Pin {
            // `targetSystem` names the same autopilot for routing: pin that one too.
            system_id: self.autopilot_sysid.or(self.target_system),
            component_id: self.target_component,
            peer: self.autopilot_peer,
            release_after: Some(Duration::from_millis(self.heartbeat_timeout_ms)),
        })
    }

    /// The APL's settings (without the signing key, see [`VasConfig::signing`]).
    pub fn apl(&self) -> MavlinkApConfig {
        MavlinkApConfig {
            vehicle: self.vehicle,
            queue_slots: self.queue_size,
            telemetry_hz: self.telemetry_hz,
            status_hz: self.status_hz,
            manager: ManagerConfig {
                heartbeat_timeout: Duration::from_millis(self.heartbeat_timeout_ms),
                request_timeout: Duration::from_millis(self.request_timeout_ms),
                retries: self.retries,
                pin: self.pin(),
                family: self.autopilot.family(),
                forward: self.forward.iter().map(|f| f.endpoint.clone()).collect(),
                // One autopilot: `autopilotSysid` (what is pinned) names it for routing too.
                target_system: self.target_system.or(self.autopilot_sysid),
                target_component: self.target_component,
                ..ManagerConfig::default()
            },
            resume_after_reboot: self.resume_after_reboot,
        }
    }

    /// The lost-link settings.
    ///
    /// # Errors
    /// An unknown action or recovery.
    pub fn link_loss(&self) -> Result<crate::val::linkloss::LinkLossConfig, ConfigLoadError> {
        let bad = |k: &str, e: String| ConfigLoadError::Invalid(format!("{k} {e}"));
        Ok(crate::val::linkloss::LinkLossConfig {
            heartbeat: self.station_heartbeat.clone(),
            radio_link: Some(self.radio_link.clone()).filter(|l| !l.is_empty()),
            timeout: Duration::from_millis(self.link_loss_timeout_ms),
            action: self
                .link_loss_action
                .parse()
                .map_err(|e| bad("linkLossAction", e))?,
            recovery: self
                .link_recovery
                .parse()
                .map_err(|e| bad("linkRecovery", e))?,
        })
    }

    /// The VAL's settings.
    pub fn val(&self) -> ValConfig {
        ValConfig {
            link_loss: self.link_loss().unwrap_or_default(),
            manual_control: self.manual_control.clone(),
            manual_timeout: Duration::from_millis(self.manual_timeout_ms),
            manual_stations: self.manual_stations.as_deref().map(|list| {
                list.split(',')
                    .map(str::trim)
                    .filter(|s| !s.is_empty())
                    .map(str::to_owned)
                    .collect()
            }),
            manual_skew: Duration::from_millis(self.manual_skew_ms),
            // Checked by `validate`.
            fence: self.fence.as_ref().and_then(|f| f.fence().ok()),
            air_log: self
                .air_log
                .clone()
                .map(|dir| (dir, self.air_log_max_mb.saturating_mul(1 << 20))),
            waypoints: crate::val::limits::WaypointLimits {
                max_alt_m: self.max_altitude_m,
                max_per_call: self.max_waypoints_per_call,
                max_queued: self.max_queued_waypoints,
                ..Default::default()
            },
            ..ValConfig::default()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_routed_system_is_the_pinned_one_unless_pinning_names_another() {
        let mut cfg = VasConfig {
            target_system: Some(7),
            ..VasConfig::default()
        };
        assert_eq!(cfg.pin().and_then(|p| p.system_id), Some(7));
        cfg.autopilot_sysid = Some(3);
        assert_eq!(cfg.pin().and_then(|p| p.system_id), Some(3));
    }

    #[test]
    fn forward_elements_name_endpoints() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("vas.xml");
        std::fs::write(
            &p,
            r#"<vas autopilot="px4"><forward endpoint="udpout:127.0.0.1:14550"/>
               <forward endpoint="udpin:0.0.0.0:14551"/></vas>"#,
        )
        .unwrap();
        let cfg = VasConfig::load(&p).unwrap();
        let mgr = cfg.apl().manager;
        assert_eq!(
            mgr.forward,
            ["udpout:127.0.0.1:14550", "udpin:0.0.0.0:14551"]
        );
        assert_eq!(mgr.family, Some(AutopilotFamily::Px4));
        std::fs::write(&p, r#"<vas><forward endpoint="nowhere"/></vas>"#).unwrap();
        assert!(matches!(
            VasConfig::load(&p),
            Err(ConfigLoadError::Invalid(_))
        ));
    }

    #[test]
    fn example_file_parses() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("vas.example.xml");
        let cfg = VasConfig::load(&path).unwrap();
        assert_eq!(cfg.vehicle, VehicleKind::Rover);
        assert_eq!(cfg.queue_size, 5);
        assert_eq!(cfg.endpoint, "udpout:127.0.0.1:14560");
    }

    #[test]
    fn link_loss_keys_are_read_and_checked() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("vas.xml");
        std::fs::write(
            &p,
            r#"<vas linkLossTimeoutMs="3000" linkLossAction="hold" linkRecovery="wait" radioLink=""/>"#,
        )
        .unwrap();
        let ll = VasConfig::load(&p).unwrap().val().link_loss;
        use crate::val::linkloss::{LinkLossAction, LinkRecovery};
        assert_eq!(ll.timeout, Duration::from_secs(3));
        assert_eq!(ll.action, LinkLossAction::Hold);
        assert_eq!(ll.recovery, LinkRecovery::Wait);
        assert_eq!(ll.radio_link, None);
        for bad in [
            r#"<vas linkLossAction="land"/>"#,
            r#"<vas linkRecovery="later"/>"#,
            r#"<vas linkLossTimeoutMs="5"/>"#,
        ] {
            std::fs::write(&p, bad).unwrap();
            let e = VasConfig::load(&p).unwrap_err().to_string();
            assert!(
                e.contains("linkLoss") || e.contains("linkRecovery"),
                "{bad}: {e}"
            );
        }
    }

    #[test]
    fn unknown_attributes_and_bad_values_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("vas.xml");
        std::fs::write(&p, r#"<vas queueSise="5"/>"#).unwrap();
        assert!(VasConfig::load(&p).is_err());
        // Each refusal names the file, the line and column, and the attribute.
        std::fs::write(&p, "<vas vehicle=\"copter\"\n     queueSise=\"5\"/>").unwrap();
        let e = VasConfig::load(&p).unwrap_err().to_string();
        assert!(
            e.contains("vas.xml:2:6: queueSise: unknown field `queueSise`"),
            "{e}"
        );
        std::fs::write(
            &p,
            "<vas>\n  <forward endpoint=\"udpout:1.2.3.4:5\" x=\"1\"/>\n</vas>",
        )
        .unwrap();
        let e = VasConfig::load(&p).unwrap_err().to_string();
        assert!(e.contains("vas.xml:2:40: x: unknown field `x`"), "{e}");
        std::fs::write(&p, "<vas queueSize=\"many\"/>").unwrap();
        let e = VasConfig::load(&p).unwrap_err().to_string();
        assert!(e.contains("vas.xml:1:6: queueSize: "), "{e}");
        std::fs::write(&p, "<vas>\n<fence>").unwrap();
        let e = VasConfig::load(&p).unwrap_err().to_string();
        assert!(e.contains("vas.xml:2:1: <fence> is never closed"), "{e}");
        std::fs::write(&p, r#"<vas queueSize="2"/>"#).unwrap();
        assert!(matches!(
            VasConfig::load(&p),
            Err(ConfigLoadError::Invalid(_))
        ));
        std::fs::write(&p, r#"<vas vehicle="copter" queueSize="8"/>"#).unwrap();
        let cfg = VasConfig::load(&p).unwrap();
        assert_eq!((cfg.vehicle, cfg.queue_size), (VehicleKind::Copter, 8));
        std::fs::write(&p, r#"<vas retries="0"/>"#).unwrap();
        assert!(matches!(
            VasConfig::load(&p),
            Err(ConfigLoadError::Invalid(_))
        ));
        std::fs::write(&p, r#"<vas requestTimeoutMs="150" retries="12"/>"#).unwrap();
        let mgr = VasConfig::load(&p).unwrap().apl().manager;
        assert_eq!(
            (mgr.request_timeout, mgr.retries),
            (Duration::from_millis(150), 12)
        );
    }

    #[test]
    fn signing_and_pinning_keys_parse_and_a_readable_key_is_refused() {
        use std::os::unix::fs::PermissionsExt;
        let dir = tempfile::tempdir().unwrap();
        let key = dir.path().join("mav.key");
        std::fs::write(&key, "11".repeat(32)).unwrap();
        std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o600)).unwrap();
        let p = dir.path().join("vas.xml");
        std::fs::write(
            &p,
            format!(
                r#"<vas autopilotSysid="3" autopilotPeer="127.0.0.1:14551">
                     <signing keyFile="{}" linkId="2"/></vas>"#,
                key.display()
            ),
        )
        .unwrap();
        let cfg = VasConfig::load(&p).unwrap();
        let signing = cfg.signing().unwrap().expect("configured");
        assert_eq!((signing.key.bytes(), signing.link_id), (&[0x11; 32], 2));
        let pin = cfg.apl().manager.pin.expect("pinned by default");
        assert_eq!(pin.system_id, Some(3));
        assert_eq!(pin.peer, "127.0.0.1:14551".parse().ok());
        std::fs::set_permissions(&key, std::fs::Permissions::from_mode(0o644)).unwrap();
        assert!(matches!(
            cfg.signing(),
            Err(ConfigLoadError::SigningKey(
                mavconn::SigningKeyLoadError::TooOpen { .. }
            ))
        ));
        std::fs::write(&p, r#"<vas pinAutopilot="false"/>"#).unwrap();
        let cfg = VasConfig::load(&p).unwrap();
        assert!(cfg.apl().manager.pin.is_none() && cfg.signing().unwrap().is_none());
        assert_eq!(cfg.val().manual_stations, None, "any station by default");
        std::fs::write(
            &p,
            r#"<vas manualStations="ground-fmo, base/fmo" manualSkewMs="500"/>"#,
        )
        .unwrap();
        let val = VasConfig::load(&p).unwrap().val();
        assert_eq!(
            val.manual_stations,
            Some(vec!["ground-fmo".to_owned(), "base/fmo".to_owned()])
        );
        assert_eq!(val.manual_skew, Duration::from_millis(500));
    }
}
