//! The `fpma` service's wire types: the arguments and results of its functions and the values of
//! its variables and events, shared by the service and the ground stations (FPMo, `usal call`);
//! [`items`] pairs each item's name with its type.
//!
//! The middleware encodes payloads with postcard, which is not self-describing: every type here
//! is a plain struct or an externally tagged enum (no `untagged`, no internally tagged enums, no
//! skipped fields), unlike the library's own JSON-oriented types, which are converted here.

pub mod items;

use serde::{Deserialize, Serialize};

use crate::exec::{flight_events, Event, EventKind, HoldHere, RetaskMode};
use crate::expand::Waypoint;
use crate::expr::Value;
use crate::geo::{GeoPoint, LocalFrame, Xy};
use crate::model::{FlightPlan, Node, NodeKind, Stage};

/// A plan variable's value.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum VarValue {
    /// A boolean.
    Bool(bool),
    /// A number.
    Number(f64),
}

impl From<Value> for VarValue {
    fn from(v: Value) -> Self {
        match v {
            Value::Bool(b) => VarValue::Bool(b),
            Value::Number(n) => VarValue::Number(n),
        }
    }
}

impl From<VarValue> for Value {
    fn from(v: VarValue) -> Self {
        match v {
            VarValue::Bool(b) => Value::Bool(b),
            VarValue::Number(n) => Value::Number(n),
        }
    }
}

/// Result of `load_plan`, `replace_plan` and of a plan file accepted by the `plans` sink.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlanLoaded {
    /// The version the plan is flown as.
    pub version: u64,
    /// The plan's name.
    pub name: String,
    /// Waypoints handed to the VAS so far.
    pub queued: u64,
    /// Always `None` now: the FPMa no longer asks for WAYPOINT_NAVIGATION (the operator does;
    /// see [`Readiness`]). Kept so older stations still decode the answer.
    pub navigation_refused: Option<String>,
}

/// A plan file that arrived on the `plans` sink and was not loaded (event `plan_rejected`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlanRejected {
    /// The file name as sent.
    pub file: String,
    /// The sending node.
    pub from: String,
    /// Why, e.g. `carpark.xml:12:7: unknown fix `P9``.
    pub reason: String,
}

/// Result of every in-flight command.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CommandAck {
    /// The plan version after the command.
    pub version: u64,
    /// The current leg after the command.
    pub leg: Option<String>,
    /// Sequence number of the next waypoint.
    pub next_seq: u64,
}

/// Arguments of `modify_leg`: attribute changes as they would be written in the XML.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModifyLeg {
    /// The leg (or scan, hold...) id.
    pub leg: String,
    /// `(attribute, value)` pairs, e.g. `("spacing", "10")`.
    pub changes: Vec<(String, String)>,
}

/// Arguments of `set_var`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SetVar {
    /// Variable name (declared in the plan, or `battery`, `alt`, `ground_speed`, `elapsed_s`).
    pub name: String,
    /// New value.
    pub value: VarValue,
}

/// Turn direction of a commanded hold.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum HoldTurn {
    /// Right.
    #[default]
    Right,
    /// Left.
    Left,
}

/// Shape of a commanded hold.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum HoldShapeArg {
    /// Straight legs joined by semicircles.
    Racetrack,
    /// Four fly-over corners (a rover).
    Rectangle,
}

/// Arguments of `hold_here` (every field optional: the defaults of [`HoldHere`]).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct HoldHereArgs {
    /// Straight-leg length, metres.
    pub length: Option<f64>,
    /// Width, metres.
    pub width: Option<f64>,
    /// Turn direction.
    pub turn: HoldTurn,
    /// Inbound course, degrees; default the present track.
    pub inbound_course: Option<f64>,
    /// Shape; default rectangle for a rover, racetrack otherwise.
    pub shape: Option<HoldShapeArg>,
}

impl From<&HoldHereArgs> for HoldHere {
    fn from(a: &HoldHereArgs) -> Self {
        use crate::model::{HoldShape, Turn};
        HoldHere {
            length: a.length,
            width: a.width,
            turn: match a.turn {
                HoldTurn::Right => Turn::R,
                HoldTurn::Left => Turn::L,
            },
            inbound_course: a.inbound_course,
            shape: a.shape.map(|s| match s {
                HoldShapeArg::Racetrack => HoldShape::Racetrack,
                HoldShapeArg::Rectangle => HoldShape::Rectangle,
            }),
        }
    }
}

/// When re-tasked points are visited.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum RetaskWhen {
    /// Interrupt the current leg, visit the points, resume the leg.
    #[default]
    Now,
    /// After the current leg (a new plan version).
    AfterCurrentLeg,
}

impl From<RetaskWhen> for RetaskMode {
    fn from(w: RetaskWhen) -> Self {
        match w {
            RetaskWhen::Now => RetaskMode::Now,
            RetaskWhen::AfterCurrentLeg => RetaskMode::AfterCurrentLeg,
        }
    }
}

/// Arguments of `retask`: points of interest, visited in nearest-neighbour order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Retask {
    /// `(lat, lon)` in degrees.
    pub points: Vec<(f64, f64)>,
    /// Altitude; default the present one.
    pub alt: Option<f64>,
    /// When.
    pub when: RetaskWhen,
}

/// Progress of the plan (variable `progress`), by distance as seed 000 measures it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Progress {
    /// Plan version (0 before any plan).
    pub version: u64,
    /// Plan name.
    pub plan: String,
    /// Current stage.
    pub stage: Option<Stage>,
    /// Current leg.
    pub leg: Option<String>,
    /// Last waypoint reached (sequence number).
    pub last_reached: Option<u64>,
    /// Sequence number of the next waypoint.
    pub next_seq: u64,
    /// Metres flown in this plan version.
    pub flown_m: f64,
    /// Metres planned: flown plus the nominal rest.
    pub planned_m: f64,
    /// `flown / planned` in [0, 1]; 1 when completed.
    pub fraction: f64,
    /// Paused by command.
    pub paused: bool,
    /// Nothing left to fly.
    pub completed: bool,
    /// The current leg is a hold.
    pub holding: bool,
    /// Seconds to the end of the plan at the speed flown so far (MAUVET's ETA, vehicle
    /// time); `None` until the vehicle has moved.
    #[serde(default)]
    pub eta_s: Option<f64>,
    /// Seconds to the end of the current leg (the target waypoint's), likewise.
    #[serde(default)]
    pub leg_eta_s: Option<f64>,
    /// The vehicle flies another ground station's mission (who, and how many items): the
    /// plan is paused until the operator resumes it.
    #[serde(default)]
    pub taken_over: Option<String>,
}

/// Whether the loaded plan waits for the operator's start (variable `ready`). The FPMa never
/// changes the flight state (pilot in command): a loaded plan fills the VAS queue and waits
/// until the operator puts the vehicle in WAYPOINT_NAVIGATION (the VAS's `change_state`, from a
/// station or `usal call`).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Readiness {
    /// Plan version (0 before any plan).
    pub version: u64,
    /// Plan name.
    pub plan: String,
    /// Waypoints are queued at a configured VAS that is not navigating: "press Start".
    pub ready: bool,
    /// For the operator, e.g. "plan `carpark` ready, press Start (WAYPOINT_NAVIGATION)".
    pub text: String,
}

/// The executive's variables and loops (variable `state`), for stations.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PlanState {
    /// Plan version (0 before any plan).
    pub version: u64,
    /// Enclosing loops of the current leg: `(id, passes done)`.
    pub loops: Vec<(String, u32)>,
    /// Plan variables and built-ins.
    pub vars: Vec<(String, VarValue)>,
    /// Sequence numbers handed to the VAS and not reached yet.
    pub queued: Vec<u64>,
}

/// One event of the executive (event `plan_event`), tagged with the plan version.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlanEvent {
    /// Plan version.
    pub version: u64,
    /// What happened.
    pub kind: PlanEventKind,
}

flight_events! {
    /// What happened (the executive's events; progress is the `progress` variable instead).
    /// Postcard tags variants by position: keep their order.
    #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
    pub enum PlanEventKind (branch: u32) {
        /// A plan was loaded (the first one, or one replacing the previous).
        PlanLoaded {
            /// Its name.
            name: String,
        },
    }
    then {
        /// Another ground station wrote the autopilot's mission: the FPMa stopped feeding the
        /// VAS and paused the plan until the operator resumes it (`resume`).
        TakenOver {
            /// Who, as the VAS saw it, e.g. `MAVLink system 250 component 190`.
            by: String,
            /// Items of the mission it wrote.
            items: u64,
        },
    }
}

/// An event in words, as a pilot reads it in a station or `usal run`'s log.
impl std::fmt::Display for PlanEventKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            PlanEventKind::PlanLoaded { name } => write!(f, "plan `{name}` loaded"),
            PlanEventKind::LegStarted { leg } => write!(f, "leg `{leg}` started"),
            PlanEventKind::LegCompleted { leg, skipped: false } => {
                write!(f, "leg `{leg}` completed")
            }
            PlanEventKind::LegCompleted { leg, skipped: true } => {
                write!(f, "leg `{leg}` skipped by command")
            }
            PlanEventKind::WaypointReached { seq, leg } => {
                write!(f, "waypoint #{seq} of leg `{leg}` reached")
            }
            PlanEventKind::IterationDone { leg, n } => write!(f, "loop `{leg}`: pass {n} done"),
            PlanEventKind::BranchTaken { leg, branch } => {
                write!(f, "alternative `{leg}`: branch {} taken", branch + 1)
            }
            PlanEventKind::StageChanged { stage } => write!(f, "{stage} stage begins"),
            PlanEventKind::PlanCompleted => f.write_str("plan completed"),
            PlanEventKind::PlanModified { leg } => write!(f, "plan changed in flight at leg `{leg}`"),
            PlanEventKind::EmergencyFired { rule } => write!(f, "emergency rule `{rule}` fired"),
            PlanEventKind::Paused => f.write_str("plan paused"),
            PlanEventKind::Resumed => f.write_str("plan resumed"),
            PlanEventKind::TakenOver { by, items } => write!(
                f,
                "TAKEN OVER: another ground station ({by}) wrote a mission of {items} items; the plan is paused until the operator resumes it"
            ),
        }
    }
}

impl PlanEvent {
    /// The wire form of an executive event; `None` for progress (published as a variable) and
    /// for the replacement notice (the service raises [`PlanEventKind::PlanLoaded`] instead).
    pub fn from_exec(e: Event) -> Option<PlanEvent> {
        let kind = match e.kind {
            EventKind::LegStarted { leg } => PlanEventKind::LegStarted { leg },
            EventKind::LegCompleted { leg, skipped } => {
                PlanEventKind::LegCompleted { leg, skipped }
            }
            EventKind::WaypointReached { seq, leg } => PlanEventKind::WaypointReached { seq, leg },
            EventKind::IterationDone { leg, n } => PlanEventKind::IterationDone { leg, n },
            EventKind::BranchTaken { leg, branch } => PlanEventKind::BranchTaken {
                leg,
                branch: u32::try_from(branch).unwrap_or(u32::MAX),
            },
            EventKind::StageChanged { stage } => PlanEventKind::StageChanged { stage },
            EventKind::PlanCompleted => PlanEventKind::PlanCompleted,
            EventKind::PlanModified { leg } => PlanEventKind::PlanModified { leg },
            EventKind::EmergencyFired { rule } => PlanEventKind::EmergencyFired { rule },
            EventKind::Paused => PlanEventKind::Paused,
            EventKind::Resumed => PlanEventKind::Resumed,
            EventKind::Progress { .. } | EventKind::PlanReplaced => return None,
        };
        Some(PlanEvent {
            version: e.version,
            kind,
        })
    }
}

/// Most waypoints a [`PlanGeometry`] carries: longer plans are thinned evenly (the last point
/// kept), so the value stays a few kilobytes, seconds on a 57600-baud radio.
pub const GEOMETRY_MAX_POINTS: usize = 1000;
/// Most legs a [`PlanGeometry`] lists; the rest are left out (`legs_truncated`).
pub const GEOMETRY_MAX_LEGS: usize = 400;

/// The plan being flown, as a station draws it (variable `plan`): its legs and its nominal
/// waypoints. Published when a plan is loaded or changed (a new version), never periodically,
/// and also answered by the function `plan_geometry`, so a station started later, or one that
/// lost the value on a radio, can draw a plan it did not upload.
///
/// Compact on purpose: waypoints are decimetre offsets from `origin` (postcard varints: a few
/// bytes each) naming their leg by index; the car-park plan takes about 600 bytes.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PlanGeometry {
    /// Plan version (0: no plan loaded).
    pub version: u64,
    /// Plan name.
    pub name: String,
    /// Where the plan came from: the file name as uploaded, or `plan` for `load_plan`.
    pub source: String,
    /// Legs and constructs in document order, stage by stage.
    pub legs: Vec<LegGeometry>,
    /// Some legs were left out ([`GEOMETRY_MAX_LEGS`]).
    pub legs_truncated: bool,
    /// Origin of the waypoint offsets, `(lat, lon)` in degrees.
    pub origin: (f64, f64),
    /// The nominal waypoints in flying order (holds and loops that wait once, marked), thinned
    /// to at most [`GEOMETRY_MAX_POINTS`].
    pub points: Vec<PlanPoint>,
    /// Waypoints of the nominal expansion before thinning.
    pub total_points: u32,
    /// Names of the plan's emergency rules, in priority order (what `emergency` takes).
    pub rules: Vec<String>,
}

/// One leg (or construct) of a [`PlanGeometry`].
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct LegGeometry {
    /// Leg id: what `goto_leg` and `modify_leg` take.
    pub id: String,
    /// Its stage.
    pub stage: Stage,
    /// Nesting depth inside loops and alternatives.
    pub depth: u8,
    /// `TF`, `hold HF`, `scan`, `iterative`...
    pub kind: String,
    /// The numeric parameters `modify_leg` can change, under their XML attribute names, with
    /// defaults resolved (metres, degrees, m/s): `spacing`, `length`, `width`, `alt`...
    pub params: Vec<(String, f32)>,
}

/// One nominal waypoint of a [`PlanGeometry`].
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PlanPoint {
    /// Decimetres east of the origin (azimuthal equidistant: [`LocalFrame`]).
    pub east_dm: i32,
    /// Decimetres north of the origin.
    pub north_dm: i32,
    /// Index of its leg in [`PlanGeometry::legs`] (`u16::MAX`: a leg left out).
    pub leg: u16,
    /// Part of a hold or loop that waits for a command or a condition (drawn once).
    pub waits: bool,
}

/// The name a station shows for a node's kind.
pub fn leg_kind_name(k: &NodeKind) -> String {
    match k {
        NodeKind::Path(p) => format!("{:?}", p.kind),
        NodeKind::Hold(h) => format!("hold {:?}", h.kind),
        NodeKind::Scan(_) => "scan".into(),
        NodeKind::Perimeter(_) => "perimeter".into(),
        NodeKind::Takeoff(_) => "takeoff".into(),
        NodeKind::Landing(_) => "landing".into(),
        NodeKind::Iterative(_) => "iterative".into(),
        NodeKind::Alternative(_) => "alternative".into(),
    }
}

/// The parameters of a leg a station may show and change (see [`LegGeometry::params`]).
fn leg_params(k: &NodeKind) -> Vec<(String, f32)> {
    let mut out: Vec<(&str, Option<f64>)> = Vec::new();
    let common = match k {
        NodeKind::Path(p) => Some(&p.common),
        NodeKind::Hold(h) => {
            out.extend([
                ("inboundCourse", Some(h.inbound_course)),
                ("length", h.length),
                ("time", h.time),
                ("width", h.width),
            ]);
            Some(&h.common)
        }
        NodeKind::Scan(sc) => {
            out.extend([
                ("spacing", Some(sc.spacing)),
                ("sweepAngle", sc.sweep_angle),
            ]);
            Some(&sc.common)
        }
        NodeKind::Perimeter(pe) => {
            out.extend([
                ("spacing", Some(pe.spacing)),
                ("rings", Some(f64::from(pe.rings))),
            ]);
            Some(&pe.common)
        }
        _ => None,
    };
    if let Some(c) = common {
        out.extend([("alt", c.alt), ("speed", c.speed)]);
    }
    out.into_iter()
        .filter_map(|(n, v)| v.map(|v| (n.to_owned(), v as f32)))
        .collect()
}

/// Decimetres, saturating (a plan spans far less than the ±214 000 km an `i32` holds).
fn dm(metres: f64) -> i32 {
    (metres * 10.0).round() as i32
}

impl PlanGeometry {
    /// The geometry of `plan` as `version`, its points thinned from `nominal` (the plan's
    /// nominal stream, as [`crate::check::CheckedPlan::nominal`] or
    /// [`crate::exec::Executive::nominal`] give it).
    pub fn of(plan: &FlightPlan, nominal: &[Waypoint], version: u64, source: &str) -> Self {
        let mut legs = Vec::new();
        fn walk(nodes: &[Node], stage: Stage, depth: u8, out: &mut Vec<LegGeometry>) {
            for n in nodes {
                out.push(LegGeometry {
                    id: n.id.clone(),
                    stage,
                    depth,
                    kind: leg_kind_name(&n.kind),
                    params: leg_params(&n.kind),
                });
                for b in n.kind.bodies() {
                    walk(b, stage, depth.saturating_add(1), out);
                }
            }
        }
        for s in Stage::ALL {
            walk(plan.stage(s), s, 0, &mut legs);
        }
        let legs_truncated = legs.len() > GEOMETRY_MAX_LEGS;
        legs.truncate(GEOMETRY_MAX_LEGS);

        let wps = nominal;
        let total_points = u32::try_from(wps.len()).unwrap_or(u32::MAX);
        let origin = wps.first().map_or((0.0, 0.0), |w| (w.lat, w.lon));
        let frame = LocalFrame::new(GeoPoint::new(origin.0, origin.1));
        // Every `stride`-th point and the last: at most GEOMETRY_MAX_POINTS, evenly spread.
        let stride = wps.len().div_ceil(GEOMETRY_MAX_POINTS - 1).max(1);
        let last = wps.len().saturating_sub(1);
        let leg_index = |id: &str| {
            legs.iter()
                .position(|l| l.id == id)
                .and_then(|i| u16::try_from(i).ok())
                .unwrap_or(u16::MAX)
        };
        let points: Vec<PlanPoint> = wps
            .iter()
            .enumerate()
            .filter(|&(i, _)| i % stride == 0 || i == last)
            .map(|(_, w)| {
                let xy = frame.to_local(GeoPoint::new(w.lat, w.lon));
                PlanPoint {
                    east_dm: dm(xy.e),
                    north_dm: dm(xy.n),
                    leg: leg_index(&w.leg),
                    waits: w.waits,
                }
            })
            .collect();
        PlanGeometry {
            version,
            name: plan.name.clone(),
            source: source.to_owned(),
            legs,
            legs_truncated,
            origin,
            points,
            total_points,
            rules: plan.emergencies.iter().map(|r| r.name.clone()).collect(),
        }
    }

    /// Where `p` is, `(lat, lon)` in degrees.
    pub fn lat_lon(&self, p: &PlanPoint) -> (f64, f64) {
        let frame = LocalFrame::new(GeoPoint::new(self.origin.0, self.origin.1));
        let g = frame.to_geo(Xy::new(
            f64::from(p.east_dm) / 10.0,
            f64::from(p.north_dm) / 10.0,
        ));
        (g.lat, g.lon)
    }

    /// The leg `p` belongs to, when listed.
    pub fn leg_of(&self, p: &PlanPoint) -> Option<&LegGeometry> {
        self.legs.get(usize::from(p.leg))
    }

    /// The nominal waypoints as a map draws them, in flying order.
    pub fn map_points(&self) -> Vec<MapPoint> {
        self.points
            .iter()
            .map(|p| {
                let (lat, lon) = self.lat_lon(p);
                MapPoint {
                    lat,
                    lon,
                    leg: self.leg_of(p).map(|l| l.id.clone()).unwrap_or_default(),
                    waits: p.waits,
                }
            })
            .collect()
    }
}

/// One nominal waypoint of a plan on a station's map ([`PlanGeometry::map_points`]).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct MapPoint {
    /// Latitude, degrees.
    pub lat: f64,
    /// Longitude, degrees.
    pub lon: f64,
    /// Its leg's id (empty for a leg the FPMa left out).
    pub leg: String,
    /// Part of a hold or loop that waits (drawn once).
    pub waits: bool,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::check::CheckedPlan;
    use crate::exec::expand_nominal;
    use crate::vehicle::VehicleParams;

    #[test]
    fn plan_events_read_as_words() {
        let cases = [
            (
                PlanEventKind::LegStarted { leg: "hold".into() },
                "leg `hold` started",
            ),
            (
                PlanEventKind::LegCompleted {
                    leg: "hold".into(),
                    skipped: true,
                },
                "leg `hold` skipped by command",
            ),
            (
                PlanEventKind::StageChanged {
                    stage: Stage::Approach,
                },
                "approach stage begins",
            ),
            (
                PlanEventKind::BranchTaken {
                    leg: "search".into(),
                    branch: 0,
                },
                "alternative `search`: branch 1 taken",
            ),
            (PlanEventKind::Paused, "plan paused"),
        ];
        for (kind, words) in cases {
            assert_eq!(kind.to_string(), words);
        }
    }

    /// Every wire type survives postcard, which refuses self-describing serde features.
    #[test]
    fn wire_types_round_trip_through_postcard() {
        fn rt<T: Serialize + for<'de> Deserialize<'de> + PartialEq + std::fmt::Debug>(v: T) {
            let bytes = postcard::to_stdvec(&v).expect("encodes");
            let back: T = postcard::from_bytes(&bytes).expect("decodes");
            assert_eq!(back, v);
        }
        rt(PlanEvent {
            version: 3,
            kind: PlanEventKind::StageChanged {
                stage: Stage::Approach,
            },
        });
        rt(PlanEvent {
            version: 1,
            kind: PlanEventKind::LegCompleted {
                leg: "area".into(),
                skipped: true,
            },
        });
        rt(Progress {
            version: 2,
            plan: "p".into(),
            stage: Some(Stage::Mission),
            leg: Some("hold".into()),
            last_reached: Some(7),
            next_seq: 8,
            flown_m: 12.5,
            planned_m: 100.0,
            fraction: 0.125,
            ..Progress::default()
        });
        rt(PlanState {
            version: 1,
            loops: vec![("laps".into(), 1)],
            vars: vec![
                ("inspect".into(), VarValue::Bool(true)),
                ("laps".into(), VarValue::Number(2.0)),
            ],
            queued: vec![8, 9],
        });
        rt(SetVar {
            name: "inspect".into(),
            value: VarValue::Bool(true),
        });
        rt(ModifyLeg {
            leg: "area".into(),
            changes: vec![("spacing".into(), "10".into())],
        });
        rt(HoldHereArgs {
            length: Some(20.0),
            shape: Some(HoldShapeArg::Rectangle),
            ..HoldHereArgs::default()
        });
        rt(Retask {
            points: vec![(41.0, 2.0)],
            alt: None,
            when: RetaskWhen::AfterCurrentLeg,
        });
        rt(PlanLoaded {
            version: 1,
            name: "p".into(),
            queued: 8,
            navigation_refused: Some("no".into()),
        });
        rt(CommandAck {
            version: 1,
            leg: None,
            next_seq: 0,
        });
        rt(PlanRejected {
            file: "a.xml".into(),
            from: "gcs".into(),
            reason: "3:1: x".into(),
        });
        let carpark = carpark();
        rt(PlanGeometry::of(
            carpark.plan(),
            carpark.nominal(),
            2,
            "rover-carpark.xml",
        ));
        rt(PlanGeometry::default());
    }

    fn carpark() -> CheckedPlan {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../config/flightplans/rover-carpark.xml"
        );
        let xml = std::fs::read_to_string(path).expect("rover-carpark.xml");
        crate::check::load(&xml, &VehicleParams::rover()).expect("valid plan")
    }

    #[test]
    fn geometry_of_the_carpark_plan_is_small_and_faithful() {
        let checked = carpark();
        let g = PlanGeometry::of(checked.plan(), checked.nominal(), 3, "rover-carpark.xml");
        assert_eq!((g.version, g.name.as_str()), (3, "castelldefels-carpark"));
        let ids: Vec<&str> = g.legs.iter().map(|l| l.id.as_str()).collect();
        assert!(ids.contains(&"hold") && ids.contains(&"area"), "{ids:?}");
        let area = g.legs.iter().find(|l| l.id == "area").unwrap();
        assert_eq!(area.kind, "scan");
        assert!(area.params.contains(&("spacing".into(), 6.0)), "{area:?}");
        let laps = g.legs.iter().position(|l| l.id == "laps").unwrap();
        assert_eq!(g.legs[laps + 1].depth, 1, "loop bodies are nested");

        // Every nominal waypoint, in order, within a decimetre, on its leg.
        let wps = expand_nominal(checked.plan().clone(), VehicleParams::rover()).unwrap();
        assert_eq!(g.points.len(), wps.len());
        assert_eq!(g.total_points as usize, wps.len());
        for (p, w) in g.points.iter().zip(&wps) {
            let (lat, lon) = g.lat_lon(p);
            let off = crate::geo::distance(GeoPoint::new(lat, lon), GeoPoint::new(w.lat, w.lon));
            assert!(off < 0.1, "{off} m off at {w:?}");
            assert_eq!(g.leg_of(p).map(|l| l.id.as_str()), Some(w.leg.as_str()));
            assert_eq!(p.waits, w.waits);
        }
        assert!(g.points.iter().any(|p| p.waits), "the HM hold waits");
        assert_eq!(g.rules, ["low-battery"]);

        // Compact enough for a radio.
        let bytes = postcard::to_stdvec(&g).unwrap().len();
        assert!(bytes < 1000, "{bytes} bytes");
    }

    #[test]
    fn long_plans_are_thinned_keeping_the_end() {
        let xml = r#"<flightPlan name="laps"><fixes>
            <fix id="A" lat="41.2750" lon="1.9870"/><fix id="B" lat="41.2755" lon="1.9870"/>
            <fix id="C" lat="41.2755" lon="1.9876"/></fixes>
            <mission><leg type="IF" fix="A"/>
              <iterative id="loop" count="700"><leg id="ab" type="TF" fix="B"/>
                <leg id="ba" type="TF" fix="A"/></iterative>
              <leg id="end" type="TF" fix="C"/></mission></flightPlan>"#;
        let checked = crate::check::load(xml, &VehicleParams::rover()).unwrap();
        let g = PlanGeometry::of(checked.plan(), checked.nominal(), 1, "plan");
        assert!(
            g.total_points as usize > GEOMETRY_MAX_POINTS,
            "{}",
            g.total_points
        );
        assert!(g.points.len() <= GEOMETRY_MAX_POINTS, "{}", g.points.len());
        assert_eq!(g.leg_of(g.points.last().unwrap()).unwrap().id, "end");
        assert!(postcard::to_stdvec(&g).unwrap().len() < 16 * 1024);
    }
}
