//! Mission composition files (`config/missions/*.xml`): which nodes exist, which services each
//! runs and with which settings. Parsed into typed specs before anything starts; every error
//! names the file, the line and column, and the element at fault.

use std::fmt;
use std::path::{Path, PathBuf};
use std::time::Duration;

use marea::xml::{Element, TextKind, XmlReadError, XmlReadErrorKind};

/// Why a mission file could not be loaded.
#[derive(Debug, thiserror::Error)]
pub enum MissionLoadError {
    /// The file could not be read.
    #[error("{}: cannot read: {source}", file.display())]
    Read {
        /// The mission file.
        file: PathBuf,
        /// What the OS said.
        source: std::io::Error,
    },
    /// The file is not well-formed XML or does not describe a valid mission.
    #[error("{}:{line}:{column}: <{element}>: {message}", file.display())]
    Invalid {
        /// The mission file.
        file: PathBuf,
        /// 1-based line of the element (or of the syntax error).
        line: usize,
        /// 1-based column.
        column: usize,
        /// The element at fault (the innermost open one for a syntax error).
        element: String,
        /// What is wrong.
        message: String,
    },
}

/// A mission: nodes and the services each runs.
#[derive(Clone, Debug, PartialEq)]
pub struct Mission {
    /// The mission's name (also the stem of its discovery domain).
    pub name: String,
    /// A fixed discovery domain; default: a unique one per run.
    pub domain: Option<String>,
    /// Whether the run is sealed with the mission's domain key (`security="on"`, the
    /// default; `"off"` opts out, loudly).
    pub sealed: bool,
    /// Limit for `--until-complete`.
    pub timeout: Option<Duration>,
    /// A radio emulator joining some nodes, if any.
    pub radio: Option<RadioSpec>,
    /// Further radios (a fleet over radios: one per vehicle's air node, each to the same
    /// ground node), after `radio`, in file order.
    pub extra_radios: Vec<RadioSpec>,
    /// A Zenoh router joining some nodes, if any.
    pub router: Option<RouterSpec>,
    /// The nodes, in file order (also the start order).
    pub nodes: Vec<NodeSpec>,
}

/// One node: a machine's worth of services sharing a namespace and a network.
#[derive(Clone, Debug, PartialEq)]
pub struct NodeSpec {
    /// Node name, e.g. `air`.
    pub name: String,
    /// Namespace of its services' items, e.g. `rover1`.
    pub namespace: Option<String>,
    /// A network.xml for its processes (domain and namespace are overridden by the mission's).
    pub network: Option<PathBuf>,
    /// The services, in start order.
    pub services: Vec<ServiceSpec>,
    /// Who may command this node's services (`<access>`, as in network.xml): given to every
    /// process of its namespace through the mission's seal.
    pub access: Option<marea::config::AccessConfig>,
}

/// A service of a node.
#[derive(Clone, Debug, PartialEq)]
pub enum ServiceSpec {
    /// The MAVLink simulator.
    Mavsim(MavsimSpec),
    /// The Virtual Autopilot.
    Vas(VasSpec),
    /// The Flight Plan Manager.
    Fpma(FpmaSpec),
    /// The ground station (run inside the launcher).
    Station(StationSpec),
    /// The Flight Monitor web station (`fmo`); `listen` is its HTTP address.
    Fmo {
        /// HTTP address (port 0: any free port).
        listen: String,
        /// Map tiles for its map (`--tiles`): `osm` (the default), `none`, an MBTiles file or
        /// a `{z}/{x}/{y}` template, local paths resolved against the mission file.
        tiles: Option<String>,
    },
    /// The Flight Plan Monitor web station (`fpmo`).
    Fpmo {
        /// HTTP address (port 0: any free port).
        listen: String,
        /// Map tiles for its map, as the FMo's.
        tiles: Option<String>,
    },
    /// A camera on the vehicle (`camera`): the node's mavsim films, the camera service
    /// publishes the frames.
    Camera(CameraSpec),
    /// The fleet mission layer (`fleet`): runs a fleet plan over the vehicles.
    Fleet {
        /// The fleet plan file.
        plan: PathBuf,
    },
    /// A program of the user's, supervised as a service of the node (`<service>`).
    Custom(CustomSpec),
    /// An autopilot not started by the mission (`<autopilot>`: SITL, a flight controller on
    /// a serial port), which the node's VAS flies instead of a `<mavsim>`.
    Autopilot(AutopilotSpec),
}

/// `<autopilot endpoint family>`.
#[derive(Clone, Debug, PartialEq)]
pub struct AutopilotSpec {
    /// Its MAVLink endpoint, as the VAS's `--endpoint` takes it (`udpin:0.0.0.0:14550`,
    /// `udpout:HOST:PORT`, `tcpout:HOST:PORT`, `serial:PATH:BAUD`).
    pub endpoint: String,
    /// Its family: `auto` (its heartbeat says), `ardupilot`, `px4` or `generic`.
    pub family: String,
}

/// `<service>`: any executable, started and supervised as a service of its node and handed
/// the node's network the way the built-ins are (`marea::NetworkConfig::from_env`).
#[derive(Clone, Debug, PartialEq)]
pub struct CustomSpec {
    /// Its name in the node (`hello`): the `[node/name]` prefix of its output.
    pub name: String,
    /// What to run.
    pub program: Program,
    /// Its arguments (`<arg value=".."/>`, in order).
    pub args: Vec<String>,
    /// Environment variables it gets (`<env name=".." value=".."/>`).
    pub env: Vec<(String, String)>,
    /// When it is started again after it ends.
    pub restart: super::supervisor::Restart,
}

/// The executable of a `<service>`.
#[derive(Clone, Debug, PartialEq)]
pub enum Program {
    /// A binary of this workspace's package (`package`), found next to `usal` and built with
    /// cargo when missing, as the built-in services are.
    Package(String),
    /// A file (`command` with a `/`, relative to the mission file).
    File(PathBuf),
    /// A program found on the `PATH` (`command` without a `/`).
    OnPath(PathBuf),
}

impl ServiceSpec {
    /// The service's short name, as in the mission file.
    pub fn kind(&self) -> &'static str {
        match self {
            ServiceSpec::Mavsim(_) => "mavsim",
            ServiceSpec::Vas(_) => "vas",
            ServiceSpec::Fpma(_) => "fpma",
            ServiceSpec::Station(_) => "station",
            ServiceSpec::Fmo { .. } => "fmo",
            ServiceSpec::Fpmo { .. } => "fpmo",
            ServiceSpec::Fleet { .. } => "fleet",
            ServiceSpec::Camera(_) => "camera",
            ServiceSpec::Custom(_) => "service",
            ServiceSpec::Autopilot(_) => "autopilot",
        }
    }

    /// Its name in the node: the kind, or a `<service>`'s own name.
    pub fn name(&self) -> &str {
        match self {
            ServiceSpec::Custom(c) => &c.name,
            other => other.kind(),
        }
    }
}

/// `<mavsim>` settings.
#[derive(Clone, Debug, PartialEq)]
pub struct MavsimSpec {
    /// rover, copter or plane.
    pub vehicle: String,
    /// `LAT,LON,ALT`.
    pub home: Option<String>,
    /// Time acceleration (overridden by `--speedup`).
    pub speedup: Option<f64>,
    /// JSON-lines event log.
    pub log: Option<PathBuf>,
    /// Battery capacity, mAh (mavsim `--battery-capacity-mah`).
    pub battery_capacity_mah: Option<f64>,
    /// Battery energy per kilometre, Wh/km (mavsim `--battery-wh-per-km`).
    pub battery_wh_per_km: Option<f64>,
    /// Points of interest its detector reports (mavsim `--poi-file`).
    pub poi_file: Option<PathBuf>,
    /// The detector's footprint radius, metres (mavsim `--sensor-radius`).
    pub sensor_radius: Option<f64>,
    /// A steady wind, `SPEED,FROM` (m/s, degrees it blows from; mavsim `--wind`).
    pub wind: Option<(f64, f64)>,
}

/// `<camera size fps hfov quality>`: a downward camera the node's `<mavsim>` renders (seeds
/// 000, 002), its frames published by the camera service.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraSpec {
    /// Picture size, pixels (`size="320x240"`, each 16-1920).
    pub size: (u32, u32),
    /// Frames a second (0.1-60, default 5).
    pub fps: f64,
    /// Horizontal field of view, degrees (5-150, default 70).
    pub hfov_deg: f64,
    /// JPEG quality of the frames to the stations (1-100, default 75).
    pub quality: u8,
}

/// `<vas>` settings.
#[derive(Clone, Debug, PartialEq)]
pub struct VasSpec {
    /// rover, copter or plane.
    pub vehicle: String,
    /// MAVLink endpoint; default: the node's mavsim.
    pub endpoint: Option<String>,
    /// Rolling-queue slots.
    pub queue_size: Option<u32>,
    /// Telemetry rate.
    pub telemetry_hz: Option<f64>,
    /// A `vas -c` file.
    pub config: Option<PathBuf>,
    /// The vehicle's own fence (`<fence>` inside `<vas>`, the plan's form): on the autopilot
    /// before the vehicle may start and for the whole flight; plans may only narrow it.
    pub fence: Option<usal_types::Fence>,
    /// A parameter file set on the autopilot at start-up (`params`; vas `--params`).
    pub params: Option<PathBuf>,
}

/// `<fpma>` settings.
#[derive(Clone, Debug, PartialEq)]
pub struct FpmaSpec {
    /// rover, aircraft or copter.
    pub vehicle: String,
    /// Waypoints queued at the VAS.
    pub lookahead: Option<u32>,
    /// The VAS to feed (service name or full prefix).
    pub vas: Option<String>,
    /// A `fpma run -c` file.
    pub config: Option<PathBuf>,
}

/// `<station>` settings: the launcher uploads `plan` and follows its progress.
#[derive(Clone, Debug, PartialEq)]
pub struct StationSpec {
    /// The flight plan to upload.
    pub plan: PathBuf,
    /// Prefix of the FPMa to fly it, e.g. `rover1/fpma`.
    pub fpma: String,
    /// Prefix of the VAS it feeds, e.g. `rover1/vas`.
    pub vas: String,
    /// rover, aircraft or copter: how the plan is expanded for the summary.
    pub vehicle: String,
    /// A plan the FPMa must refuse (`refusedPlan`), offered before `plan`: rehearses a
    /// plan check such as the geofence; accepted, it fails the run.
    pub refused_plan: Option<PathBuf>,
    /// Who presses Start once the plan is loaded (`start`).
    pub start: StartBy,
}

/// Who starts the flight once the plan is loaded and the vehicle parked (`<station start>`):
/// the pilot stays in command unless the mission hands Start to the launcher.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum StartBy {
    /// `auto`: `usal run` asks for WAYPOINT_NAVIGATION, and brings a restarted VAS back into
    /// the plan (the shipped demo: its one command flies).
    Auto,
    /// `operator`: the pilot does (the FPMo's Start, `usal call`), after a VAS restart too.
    Operator,
}

/// `<radio>`: a `marea-radio` emulator between two nodes.
#[derive(Clone, Debug, PartialEq)]
pub struct RadioSpec {
    /// The ground-side node.
    pub ground: String,
    /// The air-side node (its first service process is the gateway).
    pub air: String,
    /// Line speed.
    pub baud: u32,
    /// Byte loss probability.
    pub loss: f64,
    /// Byte corruption probability.
    pub corrupt: f64,
    /// Seed of the emulator's RNG.
    pub seed: Option<u64>,
    /// Scheduled outages (`outage="START_MS:DURATION_MS,..."`), from the radio's start: the
    /// lost-link rehearsal.
    pub outages: Vec<(u64, u64)>,
}

/// `<router>`: a Zenoh router (`usal router`) the nodes it names reach, each through a gateway
/// of its own, with no LAN in common: a system beyond one LAN, rehearsed on one host.
#[derive(Clone, Debug, PartialEq)]
pub struct RouterSpec {
    /// The nodes joined, in file order.
    pub nodes: Vec<String>,
    /// The router's listening endpoint (`listen`); port 0: a free one at start.
    pub listen: String,
    /// A node reaching the router through an emulated wide-area link (`wan` and its
    /// attributes), if any.
    pub wan: Option<WanSpec>,
    /// A rehearsed router crash (`crashMs`): killed this long after its start, then restarted.
    pub crash_after: Option<Duration>,
    /// Whether the router serves TLS with certificates made for the run (`tls`).
    pub tls: bool,
}

/// The wide-area link one node of a `<router>` reaches it through (`marea-wan`).
#[derive(Clone, Debug, PartialEq)]
pub struct WanSpec {
    /// The node (`wan`).
    pub node: String,
    /// One-way delay (`delayMs`).
    pub delay_ms: u64,
    /// Segment loss probability (`loss`).
    pub loss: f64,
    /// Bandwidth of each direction in kbit/s (`rateKbps`; 0: unlimited).
    pub rate_kbps: u64,
    /// Scheduled outages from the start (`outage="START_MS:DURATION_MS,..."`).
    pub outages: Vec<(u64, u64)>,
}

/// A validation failure before the file name is attached.
pub(crate) struct Fault {
    line: usize,
    column: usize,
    element: String,
    message: String,
}

impl Fault {
    fn at(e: &Element, message: impl fmt::Display) -> Fault {
        Fault {
            line: e.pos.line as usize,
            column: e.pos.col as usize,
            element: e.name.clone(),
            message: message.to_string(),
        }
    }
}

impl From<XmlReadError> for Fault {
    fn from(e: XmlReadError) -> Fault {
        use XmlReadErrorKind as K;
        // The element at fault: the tag for attribute errors, else the innermost open one.
        let (element, element_pos) = e
            .element
            .map_or_else(|| ("mission".to_owned(), e.pos), |el| (el.name, el.pos));
        let (pos, element, message) = match e.kind {
            K::Syntax(err) => (e.pos, element, format!("malformed XML: {err}")),
            K::Attribute(err) => (element_pos, element, format!("malformed attribute: {err}")),
            K::AttributeValue { name, source } => (
                element_pos,
                element,
                format!("attribute `{name}`: {source}"),
            ),
            K::Unclosed(name) => (e.pos, name, "not closed before the end of the file".into()),
            K::TooDeep => (e.pos, element, "elements nested too deeply".into()),
            K::Text(t) => {
                let what = match t.kind {
                    TextKind::Chars => format!("unexpected text `{}`", t.content.trim()),
                    TextKind::CData => "unexpected CDATA".into(),
                    TextKind::Reference => "unexpected entity reference".into(),
                };
                (e.pos, element, what)
            }
            K::NoRoot => {
                return Fault {
                    line: 1,
                    column: 1,
                    element: "mission".into(),
                    message: "empty file: expected a <mission> element".into(),
                }
            }
            K::SecondRoot(name) => (e.pos, name, "a second root element".into()),
        };
        Fault {
            line: pos.line as usize,
            column: pos.col as usize,
            element,
            message,
        }
    }
}

impl Mission {
    /// Reads and validates a mission file. Relative paths in it are resolved against its
    /// directory, and the files they name must exist.
    ///
    /// # Errors
    /// [`MissionLoadError`] naming the line and element at fault.
    pub fn load(path: &Path) -> Result<Mission, MissionLoadError> {
        let src = std::fs::read_to_string(path).map_err(|source| MissionLoadError::Read {
            file: path.to_owned(),
            source,
        })?;
        let base = path.parent().unwrap_or(Path::new("."));
        Mission::parse(&src, base).map_err(|f| MissionLoadError::Invalid {
            file: path.to_owned(),
            line: f.line,
            column: f.column,
            element: f.element,
            message: f.message,
        })
    }

    pub(crate) fn parse(src: &str, base: &Path) -> Result<Mission, Fault> {
        let root = marea::xml::parse_document(src)?;
        mission_from(&root, base)
    }

    /// The `<fleet>` service, with its node, if the mission has one.
    pub fn fleet(&self) -> Option<(&NodeSpec, &Path)> {
        self.nodes.iter().find_map(|n| {
            n.services.iter().find_map(|s| match s {
                ServiceSpec::Fleet { plan } => Some((n, plan.as_path())),
                _ => None,
            })
        })
    }

    /// The node named `name`.
    pub fn node(&self, name: &str) -> Option<&NodeSpec> {
        self.nodes.iter().find(|n| n.name == name)
    }

    /// Every station (one per vehicle whose plan the launcher flies), with its node, in file
    /// order.
    pub fn stations(&self) -> Vec<(&NodeSpec, &StationSpec)> {
        self.nodes
            .iter()
            .flat_map(|n| {
                n.services.iter().filter_map(move |s| match s {
                    ServiceSpec::Station(st) => Some((n, st)),
                    _ => None,
                })
            })
            .collect()
    }
}

/// An element's attributes, taken one by one; those left over are errors.
struct Attrs<'a> {
    el: &'a Element,
    left: Vec<(String, String)>,
    known: &'static [&'static str],
}

impl<'a> Attrs<'a> {
    fn new(el: &'a Element, known: &'static [&'static str]) -> Self {
        Attrs {
            el,
            left: el
                .attrs
                .iter()
                .map(|a| (a.name.clone(), a.value.clone()))
                .collect(),
            known,
        }
    }

    fn opt(&mut self, key: &str) -> Option<String> {
        let i = self.left.iter().position(|(k, _)| k == key)?;
        Some(self.left.remove(i).1)
    }

    fn req(&mut self, key: &str) -> Result<String, Fault> {
        self.opt(key)
            .ok_or_else(|| Fault::at(self.el, format!("missing attribute `{key}`")))
    }

    fn parsed<T: std::str::FromStr>(&mut self, key: &str, what: &str) -> Result<Option<T>, Fault> {
        match self.opt(key) {
            None => Ok(None),
            Some(v) => {
                v.trim().parse().map(Some).map_err(|_| {
                    Fault::at(self.el, format!("attribute `{key}`: `{v}` is not {what}"))
                })
            }
        }
    }

    fn one_of(&mut self, key: &str, allowed: &[&str], default: &str) -> Result<String, Fault> {
        let v = self.opt(key).unwrap_or_else(|| default.to_owned());
        if allowed.contains(&v.as_str()) {
            Ok(v)
        } else {
            Err(Fault::at(
                self.el,
                format!(
                    "attribute `{key}`: `{v}` is not one of {}",
                    allowed.join(", ")
                ),
            ))
        }
    }

    /// A path relative to the mission file that must exist.
    fn file(&mut self, key: &str, base: &Path) -> Result<Option<PathBuf>, Fault> {
        let Some(v) = self.opt(key) else {
            return Ok(None);
        };
        let p = base.join(&v);
        if p.is_file() {
            Ok(Some(p))
        } else {
            Err(Fault::at(
                self.el,
                format!("attribute `{key}`: no file {}", p.display()),
            ))
        }
    }

    fn finish(self) -> Result<(), Fault> {
        match self.left.first() {
            None => Ok(()),
            Some((k, _)) => Err(Fault::at(
                self.el,
                format!(
                    "unknown attribute `{k}` (expected {})",
                    if self.known.is_empty() {
                        "none".to_owned()
                    } else {
                        self.known.join(", ")
                    }
                ),
            )),
        }
    }
}

fn is_name(s: &str) -> bool {
    !s.is_empty()
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
}

fn mission_from(root: &Element, base: &Path) -> Result<Mission, Fault> {
    if root.name != "mission" {
        return Err(Fault::at(root, "the root element must be <mission>"));
    }
    let mut a = Attrs::new(root, &["name", "domain", "timeoutS", "security"]);
    let name = a.req("name")?;
    if !is_name(&name) {
        return Err(Fault::at(
            root,
            format!("name `{name}`: use letters, digits, '_' and '-'"),
        ));
    }
    let domain = a.opt("domain");
    let sealed = match a.opt("security").as_deref() {
        None | Some("on") => true,
        Some("off") => false,
        Some(other) => {
            return Err(Fault::at(
                root,
                format!("attribute `security`: `{other}` (expected `on` or `off`)"),
            ))
        }
    };
    let timeout = a
        .parsed::<f64>("timeoutS", "a number of seconds")?
        .map(|s| {
            // `try_`: a value past Duration's range (`1e30`) is an error, not a panic (found
            // by the structured fuzz test of mission files).
            match Duration::try_from_secs_f64(s) {
                Ok(d) if s > 0.0 => Ok(d),
                _ => Err(Fault::at(
                    root,
                    "attribute `timeoutS` must be a positive number of seconds",
                )),
            }
        })
        .transpose()?;
    a.finish()?;

    let mut nodes: Vec<NodeSpec> = Vec::new();
    let mut radio_el = None;
    let mut extra_radio_els = Vec::new();
    let mut router_el = None;
    for child in &root.children {
        match child.name.as_str() {
            "node" => {
                let n = node_from(child, base)?;
                if nodes.iter().any(|m| m.name == n.name) {
                    return Err(Fault::at(child, format!("duplicate node `{}`", n.name)));
                }
                nodes.push(n);
            }
            "radio" if radio_el.is_none() => radio_el = Some(child),
            "radio" => extra_radio_els.push(child),
            "router" if router_el.is_none() => router_el = Some(child),
            "router" => return Err(Fault::at(child, "a mission has one <router> at most")),
            other => {
                return Err(Fault::at(
                    child,
                    format!(
                    "unknown element <{other}> in <mission> (expected <node>, <radio> or <router>)"
                ),
                ))
            }
        }
    }
    if nodes.is_empty() {
        return Err(Fault::at(root, "a mission needs at least one <node>"));
    }
    let mut mission = Mission {
        name,
        domain,
        sealed,
        timeout,
        radio: None,
        extra_radios: Vec::new(),
        router: None,
        nodes,
    };
    if let Some(el) = radio_el {
        mission.radio = Some(radio_from(el, &mission)?);
    }
    // Several radios: each joins its own air node to the one ground node (a LAN per vehicle).
    for el in extra_radio_els {
        let spec = radio_from(el, &mission)?;
        let first = mission.radio.as_ref().expect("set before the extra ones");
        if spec.ground != first.ground {
            return Err(Fault::at(
                el,
                format!(
                    "every <radio> must join the same ground node (`{}`)",
                    first.ground
                ),
            ));
        }
        let airs = std::iter::once(first)
            .chain(&mission.extra_radios)
            .map(|r| r.air.as_str());
        if airs.clone().any(|a| a == spec.air) || spec.air == first.ground {
            return Err(Fault::at(
                el,
                format!("node `{}` already has a radio", spec.air),
            ));
        }
        mission.extra_radios.push(spec);
    }
    if let Some(el) = router_el {
        mission.router = Some(router_from(el, &mission)?);
    }
    resolve_station(root, &mut mission)?;
    Ok(mission)
}

fn router_from(el: &Element, mission: &Mission) -> Result<RouterSpec, Fault> {
    let mut a = Attrs::new(
        el,
        &[
            "nodes", "listen", "wan", "delayMs", "loss", "rateKbps", "outage", "crashMs", "tls",
        ],
    );
    let nodes: Vec<String> = a
        .req("nodes")?
        .split(',')
        .map(str::trim)
        .filter(|n| !n.is_empty())
        .map(str::to_owned)
        .collect();
    let listen = a
        .opt("listen")
        .unwrap_or_else(|| "tcp/127.0.0.1:0".to_owned());
    let wan_node = a.opt("wan");
    let delay_ms: Option<u64> = a.parsed("delayMs", "a whole number of milliseconds")?;
    let loss: Option<f64> = a.parsed("loss", "a probability")?;
    let rate_kbps: Option<u64> = a.parsed("rateKbps", "a whole number of kbit/s")?;
    let outages = match a.opt("outage") {
        None => None,
        Some(text) => Some(parse_outages(&text).map_err(|e| Fault::at(el, e))?),
    };
    let crash_after = a
        .parsed::<u64>("crashMs", "a whole number of milliseconds")?
        .map(Duration::from_millis);
    let tls = a.parsed::<bool>("tls", "true or false")?.unwrap_or(false);
    a.finish()?;
    let shaped = delay_ms.is_some() || loss.is_some() || rate_kbps.is_some() || outages.is_some();
    let wan = match wan_node {
        Some(node) => {
            if !nodes.contains(&node) {
                return Err(Fault::at(
                    el,
                    format!("`wan` names `{node}`, which is not one of `nodes`"),
                ));
            }
            let loss = loss.unwrap_or(0.0);
            if !(0.0..=1.0).contains(&loss) {
                return Err(Fault::at(el, "`loss` must be within 0..1"));
            }
            Some(WanSpec {
                node,
                delay_ms: delay_ms.unwrap_or(0),
                loss,
                rate_kbps: rate_kbps.unwrap_or(0),
                outages: outages.unwrap_or_default(),
            })
        }
        None if shaped => return Err(Fault::at(
            el,
            "delayMs, loss, rateKbps and outage shape the link of the node named by `wan`: name it",
        )),
        None => None,
    };
    if nodes.len() < 2 {
        return Err(Fault::at(
            el,
            "`nodes` must name two nodes or more (comma-separated): the router joins them",
        ));
    }
    let radio_nodes: Vec<&str> = mission
        .radio
        .iter()
        .chain(&mission.extra_radios)
        .flat_map(|r| [r.ground.as_str(), r.air.as_str()])
        .collect();
    for (i, n) in nodes.iter().enumerate() {
        let Some(node) = mission.node(n) else {
            return Err(Fault::at(el, format!("no node `{n}`")));
        };
        if nodes[..i].contains(n) {
            return Err(Fault::at(el, format!("node `{n}` is named twice")));
        }
        if radio_nodes.contains(&n.as_str()) {
            return Err(Fault::at(
                el,
                format!("node `{n}` is joined by a <radio> already"),
            ));
        }
        if node.network.is_some() {
            return Err(Fault::at(
                el,
                format!(
                    "node `{n}` is joined by the <router>: the launcher gives it its own LAN, so it must not name a network file"
                ),
            ));
        }
    }
    let valid = listen.split_once('/').is_some_and(|(proto, addr)| {
        proto == "tcp" && addr.parse::<std::net::SocketAddr>().is_ok()
    });
    if !valid {
        return Err(Fault::at(
            el,
            format!("`listen` must be a TCP endpoint like tcp/127.0.0.1:7447, found `{listen}`"),
        ));
    }
    Ok(RouterSpec {
        nodes,
        listen,
        wan,
        crash_after,
        tls,
    })
}

/// A `<mavsim home>` `LAT,LON,ALT`, or what is wrong with it: not three numbers, or a latitude,
/// longitude or altitude no place on Earth has (caught here, before anything starts, instead of
/// by a simulator failing to start again and again).
/// A `<mavsim wind>` `SPEED,FROM`: metres per second (0..60) and the direction it blows from
/// (degrees, 0..360).
fn wind(text: &str) -> Result<(f64, f64), String> {
    let parsed: Option<Vec<f64>> = text.split(',').map(|x| x.trim().parse().ok()).collect();
    let Some([speed, from]) = parsed.and_then(|v| <[f64; 2]>::try_from(v).ok()) else {
        return Err(format!(
            "wind `{text}` is not SPEED,FROM (m/s, degrees it blows from)"
        ));
    };
    if !(0.0..=60.0).contains(&speed) || !(0.0..=360.0).contains(&from) {
        return Err(format!(
            "wind `{text}`: the speed must be 0..60 m/s and the direction 0..360 degrees"
        ));
    }
    Ok((speed, from))
}

fn home(text: &str) -> Result<[f64; 3], String> {
    let parsed: Option<Vec<f64>> = text.split(',').map(|x| x.trim().parse().ok()).collect();
    let Some([lat, lon, alt]) = parsed.and_then(|v| <[f64; 3]>::try_from(v).ok()) else {
        return Err(format!("home `{text}` is not LAT,LON,ALT"));
    };
    if !(-90.0..=90.0).contains(&lat) {
        return Err(format!("home `{text}`: latitude {lat} is outside -90..90"));
    }
    if !(-180.0..=180.0).contains(&lon) {
        return Err(format!(
            "home `{text}`: longitude {lon} is outside -180..180"
        ));
    }
    if !(-500.0..=9_000.0).contains(&alt) {
        return Err(format!(
            "home `{text}`: altitude {alt} m is outside -500..9000 (metres above sea level)"
        ));
    }
    Ok([lat, lon, alt])
}

/// The home `(lat, lon)` of the `<mavsim>` among `services` (a node's), if it has one.
pub(crate) fn sim_home(services: &[ServiceSpec]) -> Option<(f64, f64)> {
    services.iter().find_map(|s| match s {
        ServiceSpec::Mavsim(m) => m
            .home
            .as_deref()
            .and_then(|h| home(h).ok())
            .map(|[lat, lon, _]| (lat, lon)),
        _ => None,
    })
}

/// A vehicle's `<fence>` (the plan's form). A `maxDistance` is measured from the fence's own
/// home, else from the node's simulator's home.
fn vehicle_fence(el: &Element, services: &[ServiceSpec]) -> Result<usal_types::Fence, Fault> {
    let pf = flightplan::parse::parse_fence(el).map_err(|e| Fault {
        line: e.line as usize,
        column: e.col as usize,
        element: el.name.clone(),
        message: e.kind.to_string(),
    })?;
    let mut fence = pf.fence;
    if !pf.home_given && fence.max_distance_m.is_some() {
        fence.home = sim_home(services).ok_or_else(|| {
            Fault::at(
                el,
                "maxDistance needs homeLat and homeLon, or a <mavsim home> before the <vas> in this node",
            )
        })?;
    }
    Ok(fence)
}

/// `fence` as the `<fence>` file `vas --fence` reads.
pub fn fence_xml(fence: &usal_types::Fence) -> String {
    use std::fmt::Write;
    let mut out = String::from("<fence");
    if let Some(d) = fence.max_distance_m {
        let (lat, lon) = fence.home;
        let _ = write!(out, r#" maxDistance="{d}" homeLat="{lat}" homeLon="{lon}""#);
    }
    if let Some(h) = fence.max_height_m {
        let _ = write!(out, r#" maxHeight="{h}""#);
    }
    let _ = writeln!(out, r#" action="{}">"#, fence.action.name());
    for (lat, lon) in &fence.polygon {
        let _ = writeln!(out, r#"  <pt lat="{lat}" lon="{lon}"/>"#);
    }
    out.push_str("</fence>\n");
    out
}

fn node_from(el: &Element, base: &Path) -> Result<NodeSpec, Fault> {
    let mut a = Attrs::new(el, &["name", "namespace", "network"]);
    let name = a.req("name")?;
    if !is_name(&name) {
        return Err(Fault::at(
            el,
            format!("name `{name}`: use letters, digits, '_' and '-'"),
        ));
    }
    let namespace = a.opt("namespace");
    let network = a.file("network", base)?;
    a.finish()?;
    let mut services = Vec::new();
    let mut access = None;
    for s in &el.children {
        let svc = match s.name.as_str() {
            "access" => {
                if access.is_some() {
                    return Err(Fault::at(s, "a second <access> in this node"));
                }
                if namespace.is_none() {
                    return Err(Fault::at(
                        s,
                        "<access> needs the node to have a namespace (its rules are given to the processes of that namespace)",
                    ));
                }
                access = Some(access_from(s)?);
                continue;
            }
            "mavsim" => {
                let mut a = Attrs::new(
                    s,
                    &[
                        "vehicle",
                        "home",
                        "speedup",
                        "log",
                        "batteryCapacityMah",
                        "batteryWhPerKm",
                        "poiFile",
                        "sensorRadius",
                        "wind",
                    ],
                );
                let spec = MavsimSpec {
                    vehicle: a.one_of("vehicle", &["rover", "copter", "plane"], "rover")?,
                    home: a.opt("home"),
                    speedup: a.parsed("speedup", "a number")?,
                    log: a.opt("log").map(|l| base.join(l)),
                    battery_capacity_mah: a.parsed("batteryCapacityMah", "a number")?,
                    battery_wh_per_km: a.parsed("batteryWhPerKm", "a number")?,
                    poi_file: a.file("poiFile", base)?,
                    sensor_radius: a.parsed("sensorRadius", "a number")?,
                    wind: match a.opt("wind") {
                        None => None,
                        Some(w) => Some(wind(&w).map_err(|e| Fault::at(s, e))?),
                    },
                };
                if spec.sensor_radius.is_some_and(|r| !(r > 0.0 && r.is_finite())) {
                    return Err(Fault::at(s, "sensorRadius must be above 0 metres"));
                }
                if spec.battery_capacity_mah.is_some_and(|x| !(x > 0.0 && x.is_finite()))
                    || spec.battery_wh_per_km.is_some_and(|x| !(x >= 0.0 && x.is_finite()))
                {
                    return Err(Fault::at(
                        s,
                        "batteryCapacityMah must be above 0 and batteryWhPerKm at least 0",
                    ));
                }
                a.finish()?;
                if let Some(Err(fault)) = spec.home.as_deref().map(home) {
                    return Err(Fault::at(s, fault));
                }
                if spec.speedup.is_some_and(|x| !(x >= 0.01 && x.is_finite())) {
                    return Err(Fault::at(s, "speedup must be at least 0.01"));
                }
                ServiceSpec::Mavsim(spec)
            }
            "vas" => {
                let mut a = Attrs::new(
                    s,
                    &[
                        "vehicle",
                        "endpoint",
                        "queueSize",
                        "telemetryHz",
                        "config",
                        "params",
                    ],
                );
                let mut spec = VasSpec {
                    vehicle: a.one_of("vehicle", &["rover", "copter", "plane"], "rover")?,
                    endpoint: a.opt("endpoint"),
                    queue_size: a.parsed("queueSize", "a whole number")?,
                    telemetry_hz: a.parsed("telemetryHz", "a number")?,
                    config: a.file("config", base)?,
                    fence: None,
                    params: a.file("params", base)?,
                };
                a.finish()?;
                for c in &s.children {
                    if c.name != "fence" || spec.fence.is_some() {
                        return Err(Fault::at(
                            c,
                            "<vas> holds at most one <fence> (the vehicle's own fence)",
                        ));
                    }
                    spec.fence = Some(vehicle_fence(c, &services)?);
                }
                ServiceSpec::Vas(spec)
            }
            "fpma" => {
                let mut a = Attrs::new(s, &["vehicle", "lookahead", "vas", "config"]);
                let spec = FpmaSpec {
                    vehicle: a.one_of("vehicle", &["rover", "aircraft", "copter"], "rover")?,
                    lookahead: a.parsed("lookahead", "a whole number")?,
                    vas: a.opt("vas"),
                    config: a.file("config", base)?,
                };
                a.finish()?;
                ServiceSpec::Fpma(spec)
            }
            "station" => {
                let mut a = Attrs::new(
                    s,
                    &["plan", "fpma", "vas", "vehicle", "refusedPlan", "start"],
                );
                let plan = a.file("plan", base)?.ok_or_else(|| {
                    Fault::at(s, "missing attribute `plan` (the flight plan to upload)")
                })?;
                let spec = StationSpec {
                    plan,
                    fpma: a.opt("fpma").unwrap_or_default(),
                    vas: a.opt("vas").unwrap_or_default(),
                    vehicle: a.one_of("vehicle", &["rover", "aircraft", "copter", ""], "")?,
                    refused_plan: a.file("refusedPlan", base)?,
                    start: match a.one_of("start", &["auto", "operator"], "auto")?.as_str() {
                        "operator" => StartBy::Operator,
                        _ => StartBy::Auto,
                    },
                };
                a.finish()?;
                ServiceSpec::Station(spec)
            }
            kind @ ("fmo" | "fpmo") => {
                let mut a = Attrs::new(s, &["listen", "tiles"]);
                let listen = a.opt("listen").unwrap_or_else(|| "127.0.0.1:0".into());
                let tiles = a.opt("tiles").map(|t| {
                    // The stations' named choices (OpenStreetMap's tiles, or none).
                    let named = ["osm", "none"];
                    if t.starts_with("http://") || t.starts_with("https://") || named.contains(&t.as_str())
                    {
                        t
                    } else {
                        base.join(t).display().to_string()
                    }
                });
                a.finish()?;
                if listen.parse::<std::net::SocketAddr>().is_err() {
                    return Err(Fault::at(
                        s,
                        format!("listen `{listen}` is not an address such as 127.0.0.1:8081"),
                    ));
                }
                if kind == "fmo" {
                    ServiceSpec::Fmo { listen, tiles }
                } else {
                    ServiceSpec::Fpmo { listen, tiles }
                }
            }
            "camera" => {
                let mut a = Attrs::new(s, &["size", "fps", "hfov", "quality"]);
                let size = a.opt("size").unwrap_or_else(|| "320x240".into());
                let size = usal_types::camera::parse_size(&size)
                    .map_err(|e| Fault::at(s, format!("size: {e}")))?;
                let spec = CameraSpec {
                    size,
                    fps: a.parsed("fps", "a number")?.unwrap_or(5.0),
                    hfov_deg: a.parsed("hfov", "a number")?.unwrap_or(70.0),
                    quality: a.parsed("quality", "a whole number from 1 to 100")?.unwrap_or(75),
                };
                a.finish()?;
                if !(0.1..=60.0).contains(&spec.fps) {
                    return Err(Fault::at(s, "fps must be from 0.1 to 60 frames a second"));
                }
                if !(5.0..=150.0).contains(&spec.hfov_deg) {
                    return Err(Fault::at(s, "hfov must be from 5 to 150 degrees"));
                }
                if !(1..=100).contains(&spec.quality) {
                    return Err(Fault::at(s, "quality must be from 1 to 100"));
                }
                ServiceSpec::Camera(spec)
            }
            "fleet" => {
                let mut a = Attrs::new(s, &["plan"]);
                let plan = a.file("plan", base)?.ok_or_else(|| {
                    Fault::at(s, "missing attribute `plan` (the fleet plan to run)")
                })?;
                a.finish()?;
                // Checked now, so a bad fleet plan stops the launch before anything starts.
                if let Err(e) = fleet::plan::load(&plan) {
                    return Err(Fault::at(s, format!("fleet plan {e}")));
                }
                ServiceSpec::Fleet { plan }
            }
            "service" => ServiceSpec::Custom(custom_from(s, base)?),
            "autopilot" => {
                let mut a = Attrs::new(s, &["endpoint", "family"]);
                let endpoint = a.req("endpoint")?;
                let family =
                    a.one_of("family", &["auto", "ardupilot", "px4", "generic"], "auto")?;
                a.finish()?;
                let scheme = endpoint.split(':').next().unwrap_or_default();
                if !["udpin", "udpout", "tcpout", "tcpin", "serial"].contains(&scheme) {
                    return Err(Fault::at(
                        s,
                        format!("endpoint `{endpoint}` is not udpin:ADDR:PORT, udpout:HOST:PORT, tcpout:HOST:PORT or serial:PATH:BAUD"),
                    ));
                }
                if services.iter().any(|x| matches!(x, ServiceSpec::Mavsim(_))) {
                    return Err(Fault::at(
                        s,
                        "a node flies either its <mavsim> or an <autopilot>, not both",
                    ));
                }
                ServiceSpec::Autopilot(AutopilotSpec { endpoint, family })
            }
            other => {
                return Err(Fault::at(
                    s,
                    format!(
                    "unknown service <{other}> in <node> (expected access, mavsim, autopilot, vas, fpma, station, fmo, fpmo, fleet, camera or service)"
                ),
                ))
            }
        };
        // Several <station>s may share a node: one per vehicle of a fleet mission.
        if !matches!(svc, ServiceSpec::Station(_))
            && services
                .iter()
                .any(|x: &ServiceSpec| x.name() == svc.name())
        {
            return Err(Fault::at(
                s,
                match &svc {
                    ServiceSpec::Custom(c) => {
                        format!("node `{name}` already runs a service named `{}`", c.name)
                    }
                    other => format!("node `{name}` already runs a {}", other.kind()),
                },
            ));
        }
        if matches!(svc, ServiceSpec::Camera(_))
            && !services.iter().any(|x| matches!(x, ServiceSpec::Mavsim(_)))
        {
            return Err(Fault::at(
                s,
                "a <camera> films through the node's <mavsim>: put one before it in this node",
            ));
        }
        if let ServiceSpec::Vas(v) = &svc {
            let has_sim = services
                .iter()
                .any(|x| matches!(x, ServiceSpec::Mavsim(_) | ServiceSpec::Autopilot(_)));
            if v.endpoint.is_none() && v.config.is_none() && !has_sim {
                return Err(Fault::at(
                    s,
                    "no `endpoint` and no <mavsim> or <autopilot> before it in this node",
                ));
            }
        }
        services.push(svc);
    }
    Ok(NodeSpec {
        name,
        namespace,
        network,
        services,
        access,
    })
}

/// A `<service name command|package restart>` with its `<arg value/>` and `<env name value/>`.
fn custom_from(el: &Element, base: &Path) -> Result<CustomSpec, Fault> {
    use super::supervisor::Restart;
    let mut a = Attrs::new(el, &["name", "command", "package", "restart"]);
    let name = a.req("name")?;
    if !is_name(&name) {
        return Err(Fault::at(
            el,
            format!("name `{name}`: use letters, digits, '_' and '-'"),
        ));
    }
    let program = match (a.opt("command"), a.opt("package")) {
        (Some(_), Some(_)) => {
            return Err(Fault::at(
                el,
                "both `command` and `package`: name the program one way",
            ))
        }
        (None, None) => {
            return Err(Fault::at(
                el,
                "missing attribute `command` (an executable) or `package` (a package of this workspace)",
            ))
        }
        (None, Some(p)) => {
            if !is_name(&p) {
                return Err(Fault::at(
                    el,
                    format!("package `{p}`: use letters, digits, '_' and '-'"),
                ));
            }
            Program::Package(p)
        }
        (Some(c), None) if c.contains('/') => {
            let p = base.join(&c);
            if !p.is_file() {
                return Err(Fault::at(
                    el,
                    format!("attribute `command`: no file {}", p.display()),
                ));
            }
            Program::File(p)
        }
        (Some(c), None) => Program::OnPath(on_path(&c).ok_or_else(|| {
            Fault::at(
                el,
                format!("attribute `command`: no program `{c}` on the PATH (give its path, e.g. ./{c})"),
            )
        })?),
    };
    let restart = match a
        .one_of("restart", &["always", "on-failure", "never"], "always")?
        .as_str()
    {
        "on-failure" => Restart::OnFailure,
        "never" => Restart::Never,
        _ => Restart::Always,
    };
    a.finish()?;
    let mut args = Vec::new();
    let mut env = Vec::new();
    for c in &el.children {
        match c.name.as_str() {
            "arg" => {
                let mut a = Attrs::new(c, &["value"]);
                args.push(a.req("value")?);
                a.finish()?;
            }
            "env" => {
                let mut a = Attrs::new(c, &["name", "value"]);
                let key = a.req("name")?;
                let value = a.req("value")?;
                a.finish()?;
                let valid = !key.is_empty()
                    && key.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
                    && !key.starts_with(|c: char| c.is_ascii_digit());
                if !valid {
                    return Err(Fault::at(
                        c,
                        format!("name `{key}` is not an environment variable name (letters, digits and '_', not starting with a digit)"),
                    ));
                }
                if key.starts_with("MAREA_") {
                    return Err(Fault::at(
                        c,
                        format!(
                            "`{key}`: the MAREA_ variables are the launcher's, set from the node"
                        ),
                    ));
                }
                env.push((key, value));
            }
            other => {
                return Err(Fault::at(
                    c,
                    format!("unknown element <{other}> in <service> (expected arg or env)"),
                ))
            }
        }
    }
    Ok(CustomSpec {
        name,
        program,
        args,
        env,
        restart,
    })
}

/// The executable `name` on the `PATH`, as a shell finds it.
fn on_path(name: &str) -> Option<PathBuf> {
    use std::os::unix::fs::PermissionsExt;
    let path = std::env::var_os("PATH")?;
    std::env::split_paths(&path)
        .map(|dir| dir.join(name))
        .find(|p| {
            std::fs::metadata(p).is_ok_and(|m| m.is_file() && m.permissions().mode() & 0o111 != 0)
        })
}

/// A node's `<access>`: `<allow kind item from/>` and `<deny kind/>`, as in network.xml.
fn access_from(el: &Element) -> Result<marea::config::AccessConfig, Fault> {
    use marea::config::{AccessConfig, AccessKind, AccessRule};
    Attrs::new(el, &[]).finish()?;
    let mut config = AccessConfig::default();
    for r in &el.children {
        let known: &'static [&'static str] = match r.name.as_str() {
            "allow" => &["kind", "item", "from"],
            "deny" => &["kind"],
            other => {
                return Err(Fault::at(
                    r,
                    format!("unknown element <{other}> in <access> (expected allow or deny)"),
                ))
            }
        };
        let mut a = Attrs::new(r, known);
        let kind = a.req("kind")?;
        let kind = AccessKind::parse(kind.trim()).ok_or_else(|| {
            Fault::at(
                r,
                format!("attribute `kind`: `{kind}` is not one of call, file, publish, gateway"),
            )
        })?;
        let mut pattern = |key: &str, default: Option<&str>| -> Result<String, Fault> {
            let v = match (a.opt(key), default) {
                (Some(v), _) => v.trim().to_owned(),
                (None, Some(d)) => d.to_owned(),
                (None, None) => return Err(Fault::at(r, format!("missing attribute `{key}`"))),
            };
            marea::name::validate_pattern(&v)
                .map_err(|e| Fault::at(r, format!("attribute `{key}`: `{v}`: {e}")))?;
            Ok(v)
        };
        if r.name == "deny" {
            a.finish()?;
            config.closed.push(kind);
        } else {
            let item = pattern("item", Some("**"))?;
            let from = pattern("from", None)?;
            a.finish()?;
            config.rules.push(AccessRule { kind, item, from });
        }
    }
    Ok(config)
}

fn radio_from(el: &Element, mission: &Mission) -> Result<RadioSpec, Fault> {
    let mut a = Attrs::new(
        el,
        &["ground", "air", "baud", "loss", "corrupt", "seed", "outage"],
    );
    let outages = match a.opt("outage") {
        None => Vec::new(),
        Some(text) => parse_outages(&text).map_err(|e| Fault::at(el, e))?,
    };
    let ground = a.req("ground")?;
    let air = a.req("air")?;
    let spec = RadioSpec {
        baud: a.parsed("baud", "a whole number")?.unwrap_or(57_600),
        loss: a.parsed("loss", "a probability")?.unwrap_or(0.0),
        corrupt: a.parsed("corrupt", "a probability")?.unwrap_or(0.0),
        seed: a.parsed("seed", "a whole number")?,
        ground,
        air,
        outages,
    };
    a.finish()?;
    for n in [&spec.ground, &spec.air] {
        if mission.node(n).is_none() {
            return Err(Fault::at(el, format!("no node `{n}`")));
        }
    }
    if spec.ground == spec.air {
        return Err(Fault::at(el, "`ground` and `air` must differ"));
    }
    for (k, p) in [("loss", spec.loss), ("corrupt", spec.corrupt)] {
        if !(0.0..=1.0).contains(&p) {
            return Err(Fault::at(el, format!("`{k}` must be within 0..1")));
        }
    }
    Ok(spec)
}

/// `START_MS:DURATION_MS[,START_MS:DURATION_MS...]`.
fn parse_outages(text: &str) -> Result<Vec<(u64, u64)>, String> {
    text.split(',')
        .map(|one| {
            let (a, b) = one
                .trim()
                .split_once(':')
                .ok_or_else(|| format!("outage `{one}` is not START_MS:DURATION_MS"))?;
            let ms = |x: &str| {
                x.trim()
                    .parse::<u64>()
                    .map_err(|_| format!("outage `{one}`: `{x}` is not a whole number of ms"))
            };
            Ok((ms(a)?, ms(b)?))
        })
        .collect()
}

/// Fills each station's defaults from the mission (the only FPMa, the VAS it feeds, its
/// vehicle) and checks that a fleet's stations name distinct FPMas.
fn resolve_station(root: &Element, mission: &mut Mission) -> Result<(), Fault> {
    // (fpma prefix, vas prefix, vehicle) of every FPMa of the mission.
    let fpmas: Vec<(String, String, String)> = mission
        .nodes
        .iter()
        .flat_map(|n| {
            n.services.iter().filter_map(move |s| match s {
                ServiceSpec::Fpma(f) => {
                    let ns = n.namespace.clone().unwrap_or_default();
                    let prefix = |svc: &str| {
                        if ns.is_empty() {
                            svc.to_owned()
                        } else {
                            format!("{ns}/{svc}")
                        }
                    };
                    let vas = match &f.vas {
                        Some(v) if v.contains('/') => v.clone(),
                        Some(v) => prefix(v),
                        None => prefix("vas"),
                    };
                    Some((prefix("fpma"), vas, f.vehicle.clone()))
                }
                _ => None,
            })
        })
        .collect();
    // The <station> elements, in the order of the parsed stations, for error positions.
    let station_els: Vec<&Element> = root
        .children
        .iter()
        .filter(|c| c.name == "node")
        .flat_map(|n| n.children.iter().filter(|c| c.name == "station"))
        .collect();
    let mut flown: Vec<(String, usize)> = Vec::new();
    let mut i = 0;
    for node in &mut mission.nodes {
        for s in &mut node.services {
            let ServiceSpec::Station(st) = s else {
                continue;
            };
            let el = station_els.get(i).copied().unwrap_or(root);
            i += 1;
            if st.fpma.is_empty() {
                match fpmas.as_slice() {
                    [(f, _, _)] => st.fpma.clone_from(f),
                    [] => {
                        return Err(Fault::at(
                            el,
                            "the <station> needs `fpma` (which FPMa flies the plan): the mission has no <fpma>",
                        ))
                    }
                    many => {
                        let names: Vec<&str> = many.iter().map(|f| f.0.as_str()).collect();
                        return Err(Fault::at(
                            el,
                            format!(
                                "the <station> needs `fpma` (which FPMa flies the plan): the mission has {} ({})",
                                many.len(),
                                names.join(", ")
                            ),
                        ));
                    }
                }
            }
            let known = fpmas.iter().find(|f| f.0 == st.fpma);
            if st.vas.is_empty() {
                st.vas = match known {
                    Some(f) => f.1.clone(),
                    None => {
                        let ns = st.fpma.rsplit_once('/').map_or("", |(ns, _)| ns);
                        if ns.is_empty() {
                            "vas".into()
                        } else {
                            format!("{ns}/vas")
                        }
                    }
                };
            }
            if st.vehicle.is_empty() {
                st.vehicle = known
                    .or(fpmas.first())
                    .map_or_else(|| "rover".into(), |f| f.2.clone());
            }
            if let Some((_, line)) = flown.iter().find(|(f, _)| *f == st.fpma) {
                return Err(Fault::at(
                    el,
                    format!(
                        "`{}` already flies the plan of the <station> at line {line}",
                        st.fpma
                    ),
                ));
            }
            flown.push((st.fpma.clone(), el.pos.line as usize));
        }
    }
    if flown.len() > 1 {
        // A fleet: every station's FPMa must be one of the mission's, so none waits forever.
        for (k, (f, _)) in flown.iter().enumerate() {
            if !fpmas.iter().any(|x| x.0 == *f) {
                let el = station_els.get(k).copied().unwrap_or(root);
                let names: Vec<&str> = fpmas.iter().map(|f| f.0.as_str()).collect();
                return Err(Fault::at(
                    el,
                    format!(
                        "fpma `{f}` is none of the mission's FPMas ({})",
                        names.join(", ")
                    ),
                ));
            }
        }
    }
    Ok(())
}

/// Structure-aware fuzzing of mission files: on stable in `cargo test`, and under cargo-fuzz
/// (`cfg(fuzzing)`) by `fuzz/fuzz_targets/mission_xml.rs`, which includes this file
/// as a module of its own (the launcher is a binary crate, which no fuzz target can depend on).
#[cfg(any(test, fuzzing))]
#[path = "mission_fuzz.rs"]
pub mod fuzz;

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(src: &str) -> Result<Mission, String> {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/missions");
        Mission::parse(src, &dir)
            .map_err(|f| format!("{}:{}: <{}>: {}", f.line, f.column, f.element, f.message))
    }

    const GOOD: &str = r#"<?xml version="1.0"?>
<mission name="m">
  <!-- a comment -->
  <node name="air" namespace="rover1">
    <mavsim vehicle="rover" home="41.275,1.987,0" speedup="5"/>
    <vas vehicle="rover" queueSize="5"/>
    <fpma vehicle="rover" lookahead="8"/>
  </node>
  <node name="ground">
    <station plan="../flightplans/rover-carpark.xml"/>
  </node>
</mission>"#;

    #[test]
    fn a_vehicle_fence_parses_in_the_plan_s_form_and_reaches_the_vas_as_written() {
        let with = |fence: &str| {
            parse(&GOOD.replace(
                r#"<vas vehicle="rover" queueSize="5"/>"#,
                &format!(r#"<vas vehicle="rover" queueSize="5">{fence}</vas>"#),
            ))
        };
        let vas = |m: &Mission| {
            m.nodes[0]
                .services
                .iter()
                .find_map(|s| match s {
                    ServiceSpec::Vas(v) => v.fence.clone(),
                    _ => None,
                })
                .expect("the vehicle's fence")
        };
        // maxDistance from the simulator's home; the polygon as written.
        let m = with(
            r#"<fence maxDistance="400" maxHeight="30" action="hold"><pt lat="41.274" lon="1.986"/><pt lat="41.277" lon="1.986"/><pt lat="41.277" lon="1.989"/></fence>"#,
        )
        .unwrap();
        let f = vas(&m);
        assert_eq!(
            (f.home, f.max_distance_m, f.max_height_m),
            ((41.275, 1.987), Some(400.0), Some(30.0))
        );
        assert_eq!(
            (f.polygon.len(), f.action),
            (3, usal_types::FenceAction::Hold)
        );
        // What the VAS reads back is the same fence.
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("fence.xml");
        std::fs::write(&file, fence_xml(&f)).unwrap();
        let back = vas::config::FenceSettings::load(&file)
            .unwrap()
            .fence()
            .unwrap();
        assert_eq!(back, f);

        let e = with(r#"<fence maxDistance="-4"/>"#).unwrap_err();
        assert!(
            e.starts_with("6:") && e.contains("<fence>") && e.contains("maxDistance"),
            "{e}"
        );
        let e = with(r#"<fence maxDistance="100"/><fence maxHeight="3"/>"#).unwrap_err();
        assert!(e.contains("at most one <fence>"), "{e}");
        for (home, says) in [
            ("141.275,1.987,0", "latitude 141.275 is outside -90..90"),
            ("41.275,200,0", "longitude 200 is outside -180..180"),
            ("41.275,1.987,12000", "altitude 12000 m is outside"),
            ("41.275,1.987", "is not LAT,LON,ALT"),
        ] {
            let bad = GOOD.replace(r#"home="41.275,1.987,0""#, &format!(r#"home="{home}""#));
            let e = parse(&bad).unwrap_err();
            assert!(e.contains(says), "{home}: {e}");
        }
        let no_home = GOOD.replace(r#" home="41.275,1.987,0""#, "").replace(
            r#"<vas vehicle="rover" queueSize="5"/>"#,
            r#"<vas vehicle="rover" queueSize="5"><fence maxDistance="100"/></vas>"#,
        );
        let e = parse(&no_home).unwrap_err();
        assert!(e.contains("maxDistance needs homeLat and homeLon"), "{e}");
    }

    #[test]
    fn a_node_s_access_rules_parse_as_in_network_xml_and_errors_name_the_line() {
        use marea::config::AccessKind;
        let with = |access: &str| {
            parse(&GOOD.replace(
                "    <fpma vehicle=\"rover\" lookahead=\"8\"/>\n",
                &format!("    <fpma vehicle=\"rover\" lookahead=\"8\"/>\n{access}"),
            ))
        };
        let m = with(
            r#"    <access>
      <allow kind="call" item="rover1/**" from="gcs/*"/>
      <allow kind="file" from="*"/>
      <deny kind="publish"/>
    </access>
"#,
        )
        .unwrap();
        let a = m.nodes[0].access.as_ref().expect("the air node's rules");
        assert_eq!(a.rules.len(), 2);
        assert_eq!(
            (a.rules[0].kind, &*a.rules[0].item, &*a.rules[0].from),
            (AccessKind::Call, "rover1/**", "gcs/*")
        );
        assert_eq!(a.rules[1].item, "**", "item defaults to every item");
        assert_eq!(a.closed, [AccessKind::Publish]);
        assert!(m.nodes[1].access.is_none());
        for (bad, says) in [
            (
                r#"<access><allow kind="fly" from="*"/></access>"#,
                "`fly` is not one of",
            ),
            (
                r#"<access><allow kind="call"/></access>"#,
                "missing attribute `from`",
            ),
            (
                r#"<access><allow kind="call" from="a//b"/></access>"#,
                "attribute `from`",
            ),
            (
                r#"<access><grant kind="call"/></access>"#,
                "unknown element <grant>",
            ),
            ("<access/><access/>", "a second <access>"),
        ] {
            let e = with(&format!("    {bad}\n")).unwrap_err();
            assert!(e.starts_with("8:") && e.contains(says), "{bad}: {e}");
        }
        let e = parse(&GOOD.replace(
            "    <station plan",
            "    <access><allow kind=\"call\" from=\"*\"/></access>\n    <station plan",
        ))
        .unwrap_err();
        assert!(e.contains("needs the node to have a namespace"), "{e}");
    }

    #[test]
    fn a_mission_is_sealed_unless_it_says_security_off() {
        assert!(parse(GOOD).unwrap().sealed, "sealed by default");
        let with = |v: &str| {
            parse(&GOOD.replace(
                r#"<mission name="m">"#,
                &format!(r#"<mission name="m" security="{v}">"#),
            ))
        };
        assert!(with("on").unwrap().sealed);
        assert!(!with("off").unwrap().sealed);
        let err = with("maybe").unwrap_err();
        assert!(
            err.contains("2:1: <mission>") && err.contains("`maybe`"),
            "{err}"
        );
    }

    #[test]
    fn fpmo_tiles_resolve_against_the_mission_file_and_urls_stay() {
        let with = |fpmo: &str| {
            parse(&GOOD.replace(
                "    <station plan",
                &format!("    {fpmo}\n    <station plan"),
            ))
        };
        let m = with(r#"<fpmo tiles="../maps/field.mbtiles"/>"#).unwrap();
        let Some(ServiceSpec::Fpmo { tiles: Some(t), .. }) = m.nodes[1].services.first() else {
            panic!("no fpmo with tiles: {:?}", m.nodes[1].services.len());
        };
        assert!(t.ends_with("config/missions/../maps/field.mbtiles"), "{t}");
        let m = with(r#"<fpmo tiles="https://tiles.example/{z}/{x}/{y}.png"/>"#).unwrap();
        let Some(ServiceSpec::Fpmo { tiles: Some(t), .. }) = m.nodes[1].services.first() else {
            panic!("no fpmo with tiles");
        };
        assert_eq!(t, "https://tiles.example/{z}/{x}/{y}.png");
        let m = with(r#"<fmo tiles="none"/>"#).unwrap();
        let Some(ServiceSpec::Fmo { tiles: Some(t), .. }) = m.nodes[1].services.first() else {
            panic!("no fmo with tiles");
        };
        assert_eq!(t, "none");
    }

    #[test]
    fn a_valid_mission_parses_and_the_station_finds_its_fpma() {
        let m = parse(GOOD).unwrap();
        assert_eq!(m.name, "m");
        assert_eq!(m.nodes.len(), 2);
        let kinds: Vec<_> = m.nodes[0].services.iter().map(|s| s.kind()).collect();
        assert_eq!(kinds, ["mavsim", "vas", "fpma"]);
        let (node, st) = m.stations()[0];
        assert_eq!(node.name, "ground");
        assert_eq!(st.fpma, "rover1/fpma");
        assert_eq!(st.vas, "rover1/vas");
        assert_eq!(st.vehicle, "rover");
        assert_eq!(st.start, StartBy::Auto);
    }

    #[test]
    fn a_station_is_started_by_the_launcher_or_the_operator() {
        let with = |start: &str| {
            parse(&GOOD.replace(
                r#"<station plan="../flightplans/rover-carpark.xml"/>"#,
                &format!(r#"<station plan="../flightplans/rover-carpark.xml" start="{start}"/>"#),
            ))
        };
        let m = with("operator").unwrap();
        assert_eq!(m.stations()[0].1.start, StartBy::Operator);
        assert_eq!(with("auto").unwrap().stations()[0].1.start, StartBy::Auto);
        let e = with("pilot").unwrap_err();
        assert!(e.contains("<station>: attribute `start`"), "{e}");
        assert!(e.contains("operator"), "{e}");
    }

    #[test]
    fn a_service_of_the_user_s_runs_a_package_a_file_or_a_program_on_the_path() {
        use crate::run::supervisor::Restart;
        let with = |svc: &str| {
            parse(&GOOD.replace(
                r#"<fpma vehicle="rover" lookahead="8"/>"#,
                &format!(r#"<fpma vehicle="rover" lookahead="8"/>{svc}"#),
            ))
        };
        let custom = |m: &Mission| {
            m.nodes[0]
                .services
                .iter()
                .find_map(|s| match s {
                    ServiceSpec::Custom(c) => Some(c.clone()),
                    _ => None,
                })
                .expect("a <service>")
        };
        let m = with(
            r#"<service name="hello" package="hello-service" restart="on-failure">
                 <arg value="--greeting"/><arg value="hi there"/>
                 <env name="HELLO_VEHICLE" value="rover1"/>
               </service>"#,
        )
        .unwrap();
        let c = custom(&m);
        assert_eq!(c.program, Program::Package("hello-service".into()));
        assert_eq!(c.args, ["--greeting", "hi there"]);
        assert_eq!(c.env, [("HELLO_VEHICLE".to_owned(), "rover1".to_owned())]);
        assert_eq!(c.restart, Restart::OnFailure);
        assert_eq!(
            m.nodes[0].services.last().map(ServiceSpec::name),
            Some("hello")
        );
        // A program on the PATH (sh is on every PATH), found when the mission is read.
        let c = custom(&with(r#"<service name="s" command="sh"/>"#).unwrap());
        assert!(
            matches!(&c.program, Program::OnPath(p) if p.ends_with("sh")),
            "{c:?}"
        );
        assert_eq!(c.restart, Restart::Always);
        // A file relative to the mission.
        let c = custom(&with(r#"<service name="s" command="./rover-demo.xml"/>"#).unwrap());
        assert!(matches!(&c.program, Program::File(p) if p.ends_with("rover-demo.xml")));
        // Two services of the user's with different names may share a node; not one name twice.
        let two = r#"<service name="a" command="sh"/><service name="b" command="sh"/>"#;
        assert_eq!(with(two).unwrap().nodes[0].services.len(), 5);
        for (bad, says) in [
            (r#"<service command="sh"/>"#, "missing attribute `name`"),
            (
                r#"<service name="a b" command="sh"/>"#,
                "use letters, digits",
            ),
            (r#"<service name="s"/>"#, "missing attribute `command`"),
            (
                r#"<service name="s" command="sh" package="p"/>"#,
                "both `command` and `package`",
            ),
            (
                r#"<service name="s" command="no-such-program-here"/>"#,
                "no program `no-such-program-here` on the PATH",
            ),
            (r#"<service name="s" command="./absent"/>"#, "no file"),
            (
                r#"<service name="s" command="sh" restart="sometimes"/>"#,
                "`sometimes` is not one of always, on-failure, never",
            ),
            (
                r#"<service name="s" command="sh"><arg/></service>"#,
                "<arg>: missing attribute `value`",
            ),
            (
                r#"<service name="s" command="sh"><env name="MAREA_DOMAIN" value="x"/></service>"#,
                "the MAREA_ variables are the launcher's",
            ),
            (
                r#"<service name="s" command="sh"><env name="1X" value="x"/></service>"#,
                "not an environment variable name",
            ),
            (
                r#"<service name="s" command="sh"><flag/></service>"#,
                "unknown element <flag> in <service>",
            ),
            (
                r#"<service name="s" command="sh"/><service name="s" command="sh"/>"#,
                "already runs a service named `s`",
            ),
            (
                r#"<service name="vas" command="sh"/>"#,
                "already runs a service named `vas`",
            ),
        ] {
            let e = with(bad).unwrap_err();
            assert!(e.contains(says), "{bad}: {e}");
        }
    }

    #[test]
    fn errors_name_the_element_and_line() {
        let e = parse(&GOOD.replace("queueSize=\"5\"", "queueSize=\"five\"")).unwrap_err();
        assert!(e.starts_with("6:5: <vas>: attribute `queueSize`"), "{e}");
        let e = parse(&GOOD.replace("<fpma ", "<fmpa ")).unwrap_err();
        assert!(e.starts_with("7:5: <fmpa>: unknown service"), "{e}");
        let e = parse(&GOOD.replace("lookahead=", "lookahaed=")).unwrap_err();
        assert!(e.contains("<fpma>: unknown attribute `lookahaed`"), "{e}");
        // An unclosed <node>: the syntax error names it and the line of the mismatch.
        let e = parse(&GOOD.replace("  </node>\n</mission>", "</mission>")).unwrap_err();
        assert!(
            e.starts_with("11:") && e.contains("<node>: malformed XML"),
            "{e}"
        );
        let e = parse(&GOOD.replace("rover-carpark", "missing")).unwrap_err();
        assert!(
            e.starts_with("10:5: <station>: attribute `plan`: no file"),
            "{e}"
        );
        let e = parse(&GOOD.replace("<mavsim vehicle=\"rover\"", "<mavsim vehicle=\"boat\""))
            .unwrap_err();
        assert!(e.contains("<mavsim>") && e.contains("boat"), "{e}");
        let e = parse(&GOOD.replace("<node name=\"ground\">", "<node name=\"air\">")).unwrap_err();
        assert!(e.starts_with("9:3: <node>: duplicate node"), "{e}");
        let e = parse("<mission name=\"x\"><node name=\"a\"><vas/></node></mission>").unwrap_err();
        assert!(e.contains("<vas>: no `endpoint`"), "{e}");
        let e = parse("").unwrap_err();
        assert!(e.contains("empty file"), "{e}");
        let e = parse("<mission name=\"x\">\n<node name=\"a\">\n</mission>").unwrap_err();
        assert!(e.starts_with("3:") && e.contains("<node>"), "{e}");
    }

    const FLEET: &str = r#"<mission name="f">
  <node name="air1" namespace="rover1">
    <mavsim/><vas/><fpma/>
  </node>
  <node name="air2" namespace="rover2">
    <mavsim/><vas/><fpma vehicle="aircraft"/>
  </node>
  <node name="ground">
    <station plan="../flightplans/rover-demo.xml" fpma="rover1/fpma"/>
    <station plan="../flightplans/rover-carpark.xml" fpma="rover2/fpma"/>
  </node>
</mission>"#;

    #[test]
    fn a_fleet_has_one_station_per_vehicle_each_with_its_vas_and_vehicle() {
        let m = parse(FLEET).unwrap();
        let st: Vec<_> = m
            .stations()
            .iter()
            .map(|(n, s)| {
                (
                    n.name.as_str(),
                    s.fpma.as_str(),
                    s.vas.as_str(),
                    s.vehicle.as_str(),
                )
            })
            .collect();
        assert_eq!(
            st,
            [
                ("ground", "rover1/fpma", "rover1/vas", "rover"),
                ("ground", "rover2/fpma", "rover2/vas", "aircraft")
            ]
        );
    }

    #[test]
    fn fleet_errors_name_the_station_and_its_line() {
        let e = parse(&FLEET.replace(" fpma=\"rover2/fpma\"", "")).unwrap_err();
        assert!(
            e.starts_with("10:5: <station>: the <station> needs `fpma`")
                && e.contains("rover1/fpma, rover2/fpma"),
            "{e}"
        );
        let e = parse(&FLEET.replace("fpma=\"rover2/fpma\"", "fpma=\"rover1/fpma\"")).unwrap_err();
        assert!(
            e.starts_with(
                "10:5: <station>: `rover1/fpma` already flies the plan of the <station> at line 9"
            ),
            "{e}"
        );
        let e = parse(&FLEET.replace("fpma=\"rover2/fpma\"", "fpma=\"rover3/fpma\"")).unwrap_err();
        assert!(
            e.starts_with("10:5: <station>: fpma `rover3/fpma` is none of the mission's FPMas"),
            "{e}"
        );
        // Other services stay one per node.
        let e = parse(&FLEET.replace("<mavsim/><vas/><fpma/>", "<mavsim/><vas/><fpma/><fpma/>"))
            .unwrap_err();
        assert!(e.contains("node `air1` already runs a fpma"), "{e}");
    }

    #[test]
    fn a_router_joins_the_nodes_it_names_and_refuses_what_cannot_work() {
        let with = |r: &str| parse(&FLEET.replace("</mission>", &format!("{r}\n</mission>")));
        let m = with(r#"<router nodes="air1, air2,ground"/>"#).unwrap();
        assert_eq!(
            m.router,
            Some(RouterSpec {
                nodes: vec!["air1".into(), "air2".into(), "ground".into()],
                listen: "tcp/127.0.0.1:0".into(),
                wan: None,
                crash_after: None,
                tls: false,
            })
        );
        let m = with(
            r#"<router nodes="air1,ground" wan="ground" delayMs="75" loss="0.01" rateKbps="2000" outage="45000:30000" crashMs="20000"/>"#,
        )
        .unwrap();
        let r = m.router.unwrap();
        assert_eq!(
            r.wan,
            Some(WanSpec {
                node: "ground".into(),
                delay_ms: 75,
                loss: 0.01,
                rate_kbps: 2000,
                outages: vec![(45_000, 30_000)],
            })
        );
        assert_eq!(r.crash_after, Some(Duration::from_secs(20)));
        let m = with(r#"<router nodes="air1,ground" listen="tcp/0.0.0.0:7447"/>"#).unwrap();
        assert_eq!(
            m.router.map(|r| r.listen).as_deref(),
            Some("tcp/0.0.0.0:7447")
        );
        for (router, says) in [
            (r#"<router nodes="air1"/>"#, "two nodes or more"),
            (r#"<router nodes="air1,nowhere"/>"#, "no node `nowhere`"),
            (
                r#"<router nodes="air1,air1"/>"#,
                "node `air1` is named twice",
            ),
            (
                r#"<router nodes="air1,ground" listen="udp/1.2.3.4:1"/>"#,
                "a TCP endpoint",
            ),
            (
                r#"<radio ground="ground" air="air1"/><router nodes="air1,air2"/>"#,
                "node `air1` is joined by a <radio> already",
            ),
            (
                r#"<router nodes="air1,ground"/><router nodes="air2,ground"/>"#,
                "one <router> at most",
            ),
            (r#"<router nodes="air1,ground" delayMs="75"/>"#, "name it"),
            (
                r#"<router nodes="air1,ground" wan="air2"/>"#,
                "not one of `nodes`",
            ),
            (
                r#"<router nodes="air1,ground" wan="ground" loss="2"/>"#,
                "within 0..1",
            ),
        ] {
            let e = with(router).unwrap_err();
            assert!(e.contains("<router>") && e.contains(says), "{router}: {e}");
        }
        let e = parse(
            &FLEET
                .replace(
                    "<node name=\"ground\">",
                    "<node name=\"ground\" network=\"../network.xml\">",
                )
                .replace("</mission>", "<router nodes=\"air1,ground\"/>\n</mission>"),
        )
        .unwrap_err();
        assert!(e.contains("must not name a network file"), "{e}");
    }

    #[test]
    fn a_fleet_over_radios_has_one_radio_per_air_node_to_one_ground_node() {
        let radios = |r: &str| parse(&FLEET.replace("</mission>", &format!("{r}\n</mission>")));
        let m = radios(
            r#"<radio ground="ground" air="air1"/><radio ground="ground" air="air2" seed="3"/>"#,
        )
        .unwrap();
        assert_eq!(m.radio.as_ref().unwrap().air, "air1");
        assert_eq!(m.extra_radios.len(), 1);
        assert_eq!(
            (m.extra_radios[0].air.as_str(), m.extra_radios[0].seed),
            ("air2", Some(3))
        );
        let e = radios(r#"<radio ground="ground" air="air1"/><radio ground="air2" air="air1"/>"#)
            .unwrap_err();
        assert!(
            e.starts_with("12:") && e.contains("must join the same ground node (`ground`)"),
            "{e}"
        );
        let e = radios(r#"<radio ground="ground" air="air1"/><radio ground="ground" air="air1"/>"#)
            .unwrap_err();
        assert!(e.contains("node `air1` already has a radio"), "{e}");
    }

    #[test]
    fn a_camera_films_through_its_nodes_mavsim_with_sizes_and_rates_in_range() {
        let with = |node: &str| parse(&FLEET.replace("<mavsim/><vas/><fpma/>", node));
        let m =
            with(r#"<mavsim/><camera size="640x480" fps="2" hfov="90"/><vas/><fpma/>"#).unwrap();
        let cam = m.nodes[0].services.iter().find_map(|s| match s {
            ServiceSpec::Camera(c) => Some(c.clone()),
            _ => None,
        });
        assert_eq!(
            cam,
            Some(CameraSpec {
                size: (640, 480),
                fps: 2.0,
                hfov_deg: 90.0,
                quality: 75,
            })
        );
        let e = with(r#"<camera/><mavsim/><vas/><fpma/>"#).unwrap_err();
        assert!(
            e.contains("<camera>: a <camera> films through the node's <mavsim>"),
            "{e}"
        );
        let e = with(r#"<mavsim/><camera size="8x8"/><vas/><fpma/>"#).unwrap_err();
        assert!(
            e.contains("<camera>: size: `8` in `8x8` is not a size from 16"),
            "{e}"
        );
        let e = with(r#"<mavsim/><camera fps="0"/><vas/><fpma/>"#).unwrap_err();
        assert!(e.contains("fps must be from 0.1 to 60"), "{e}");
        let e = with(r#"<mavsim/><camera quality="0"/><vas/><fpma/>"#).unwrap_err();
        assert!(e.contains("quality must be from 1 to 100"), "{e}");
    }

    #[test]
    fn a_fleet_service_names_a_valid_fleet_plan() {
        let with = |fleet: &str| {
            parse(&FLEET.replace(
                "<node name=\"ground\">",
                &format!("<node name=\"ground\">{fleet}"),
            ))
        };
        let m = with(r#"<fleet plan="../fleetplans/search.xml"/>"#).unwrap();
        let (node, plan) = m.fleet().unwrap();
        assert_eq!(node.name, "ground");
        assert!(plan.ends_with("fleetplans/search.xml"));
        let e = with(r#"<fleet plan="../fleetplans/nope.xml"/>"#).unwrap_err();
        assert!(
            e.starts_with("8:23: <fleet>: attribute `plan`: no file"),
            "{e}"
        );
        let e = with(r#"<fleet/>"#).unwrap_err();
        assert!(e.contains("<fleet>: missing attribute `plan`"), "{e}");
        let e = with(r#"<mavsim poiFile="../search/pois.txt" sensorRadius="-1"/>"#).unwrap_err();
        assert!(e.contains("<mavsim>: sensorRadius must be above 0"), "{e}");
    }

    #[test]
    fn the_mavsim_battery_is_configured_and_checked() {
        let with = |attrs: &str| {
            parse(&GOOD.replace("speedup=\"5\"/>", &format!("speedup=\"5\" {attrs}/>")))
        };
        let m = with(r#"batteryCapacityMah="60" batteryWhPerKm="2""#).unwrap();
        let ServiceSpec::Mavsim(sim) = &m.nodes[0].services[0] else {
            panic!("mavsim first");
        };
        assert_eq!(
            (sim.battery_capacity_mah, sim.battery_wh_per_km),
            (Some(60.0), Some(2.0))
        );
        let e = with(r#"batteryCapacityMah="0""#).unwrap_err();
        assert!(
            e.contains("<mavsim>") && e.contains("batteryCapacityMah"),
            "{e}"
        );
        let e = with(r#"batteryWhPerKm="lots""#).unwrap_err();
        assert!(e.contains("batteryWhPerKm"), "{e}");
        let m = with(r#"wind="6,270""#).unwrap();
        let ServiceSpec::Mavsim(sim) = &m.nodes[0].services[0] else {
            panic!("mavsim first");
        };
        assert_eq!(sim.wind, Some((6.0, 270.0)));
        for bad in [r#"wind="70,0""#, r#"wind="6""#, r#"wind="6,400""#] {
            let e = with(bad).unwrap_err();
            assert!(e.contains("<mavsim>") && e.contains("wind"), "{bad}: {e}");
        }
    }

    #[test]
    fn random_input_is_an_error_never_a_panic() {
        let bytes = GOOD.as_bytes();
        for cut in 0..bytes.len() {
            let s = String::from_utf8_lossy(&bytes[..cut]);
            let _ = parse(&s);
        }
    }

    #[test]
    fn the_failsafe_mission_names_its_outages_and_refused_plan() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/missions");
        let m = Mission::load(&dir.join("rover-failsafe.xml")).unwrap();
        assert_eq!(
            m.radio.as_ref().map(|r| r.outages.clone()),
            Some(vec![(45_000, 12_000)])
        );
        let (_, st) = m.stations()[0];
        assert!(st
            .refused_plan
            .as_ref()
            .is_some_and(|p| p.ends_with("rover-failsafe-outside.xml")));
        assert_eq!(
            parse_outages("1:2, 30000:500"),
            Ok(vec![(1, 2), (30_000, 500)])
        );
        for bad in ["", "5", "a:1", "1:-2"] {
            assert!(parse_outages(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn the_shipped_missions_parse() {
        let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("config/missions");
        for entry in std::fs::read_dir(&dir).unwrap() {
            let p = entry.unwrap().path();
            if p.extension().is_some_and(|e| e == "xml") {
                Mission::load(&p).unwrap_or_else(|e| panic!("{e}"));
            }
        }
    }
}
