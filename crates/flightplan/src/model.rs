//! The typed flight-plan model: what a parsed and validated XML plan is. Every type is serde
//! serialisable so the service can publish plans, legs and waypoints as they are.

use crate::expr::{Condition, Value, ValueType};
use crate::geo::GeoPoint;
use crate::vehicle::{VehicleKind, VehicleParams};
use crate::xml::Element;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt;

/// A flight plan: declarations and the five stages, each a sequence of nodes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FlightPlan {
    /// `name` attribute.
    pub name: String,
    /// The document's own `version` attribute (the author's revision; the executive keeps its own
    /// increasing plan version on top).
    pub revision: Option<u32>,
    /// Altitude reference, as written (`MSL`, `AGL`, `REL`).
    pub alt_ref: String,
    /// `defaultSpeed`, m/s.
    pub default_speed: Option<f64>,
    /// `vehicle`: the kind of vehicle the plan is written for, when it says; a plan is refused
    /// for another kind (and `fpma expand` uses it when no `--vehicle` is given).
    #[serde(default)]
    pub vehicle: Option<VehicleKind>,
    /// Where `vehicle` is written (line, column; 0 for plans built in code): the check names it
    /// when the plan is for another kind.
    #[serde(default)]
    pub vehicle_at: (u32, u32),
    /// Declared variables.
    pub variables: Vec<VarDecl>,
    /// Named fixes.
    pub fixes: BTreeMap<String, Fix>,
    /// `<takeoff>` as a one-node stage (empty when absent).
    pub takeoff: Vec<Node>,
    /// `<departure>`.
    pub departure: Vec<Node>,
    /// `<mission>`.
    pub mission: Vec<Node>,
    /// `<approach>`.
    pub approach: Vec<Node>,
    /// `<landing>` as a one-node stage (empty when absent).
    pub landing: Vec<Node>,
    /// `<emergency>` rules in priority order.
    pub emergencies: Vec<EmergencyRule>,
    /// `<fence>`: where the vehicle must stay (`crate::fence`).
    #[serde(default)]
    pub fence: Option<PlanFence>,
}

/// A plan's `<fence>`: the fence (its home resolved: the element's, else the plan's first
/// waypoint) and where it is written.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlanFence {
    /// The fence, as the VAS and the autopilot get it.
    pub fence: usal_types::Fence,
    /// Whether `homeLat`/`homeLon` were given (else the home is the first waypoint's).
    pub home_given: bool,
    /// Line of the `<fence>` element.
    pub line: u32,
    /// Column.
    pub col: u32,
}

/// The stages of a plan, flown in this order.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Stage {
    /// Take-off.
    Takeoff,
    /// Departure procedure.
    Departure,
    /// The mission proper.
    Mission,
    /// Approach procedure.
    Approach,
    /// Landing.
    Landing,
}

impl Stage {
    /// All stages in flying order.
    pub const ALL: [Stage; 5] = [
        Stage::Takeoff,
        Stage::Departure,
        Stage::Mission,
        Stage::Approach,
        Stage::Landing,
    ];
    /// The stage's XML element name.
    pub fn name(self) -> &'static str {
        match self {
            Stage::Takeoff => "takeoff",
            Stage::Departure => "departure",
            Stage::Mission => "mission",
            Stage::Approach => "approach",
            Stage::Landing => "landing",
        }
    }
    /// The stage named `s`.
    pub fn from_name(s: &str) -> Option<Stage> {
        Stage::ALL.into_iter().find(|st| st.name() == s)
    }
    /// The stage after this one.
    pub fn next(self) -> Option<Stage> {
        let i = Stage::ALL.iter().position(|s| *s == self)?;
        Stage::ALL.get(i + 1).copied()
    }
}

impl fmt::Display for Stage {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.name())
    }
}

impl FlightPlan {
    /// What the plan's altitudes are measured from (`altRef`, validated when parsed; `MSL`
    /// when absent or, for a plan built in code, unknown).
    pub fn altitude_reference(&self) -> usal_types::AltRef {
        self.alt_ref.parse().unwrap_or(usal_types::AltRef::Msl)
    }

    /// The stage a landing plan's landing sequence begins with: its approach, or its landing
    /// where there is no approach; `None` for a plan that does not land.
    pub fn landing_begins(&self) -> Option<Stage> {
        if self.landing.is_empty() {
            None
        } else if self.approach.is_empty() {
            Some(Stage::Landing)
        } else {
            Some(Stage::Approach)
        }
    }

    /// The nodes of stage `s`.
    pub fn stage(&self, s: Stage) -> &[Node] {
        match s {
            Stage::Takeoff => &self.takeoff,
            Stage::Departure => &self.departure,
            Stage::Mission => &self.mission,
            Stage::Approach => &self.approach,
            Stage::Landing => &self.landing,
        }
    }
    /// The nodes of stage `s`, mutable.
    pub fn stage_mut(&mut self, s: Stage) -> &mut Vec<Node> {
        match s {
            Stage::Takeoff => &mut self.takeoff,
            Stage::Departure => &mut self.departure,
            Stage::Mission => &mut self.mission,
            Stage::Approach => &mut self.approach,
            Stage::Landing => &mut self.landing,
        }
    }
    /// The declared type of variable `name`, including built-ins.
    pub fn var_type(&self, name: &str) -> Option<ValueType> {
        if BUILTINS.contains(&name) {
            return Some(ValueType::Number);
        }
        self.variables.iter().find(|v| v.name == name).map(|v| v.ty)
    }
    /// Finds a node anywhere in the plan by id.
    pub fn find(&self, id: &str) -> Option<&Node> {
        fn walk<'a>(nodes: &'a [Node], id: &str) -> Option<&'a Node> {
            for n in nodes {
                if n.id == id {
                    return Some(n);
                }
                for body in n.kind.bodies() {
                    if let Some(f) = walk(body, id) {
                        return Some(f);
                    }
                }
            }
            None
        }
        Stage::ALL.iter().find_map(|s| walk(self.stage(*s), id))
    }
}

/// Numeric built-in variables every condition may read. `iteration` is the innermost loop's
/// completed-pass count; the others come from telemetry.
pub const BUILTINS: [&str; 5] = ["iteration", "elapsed_s", "alt", "ground_speed", "battery"];

/// A declared plan variable.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VarDecl {
    /// Name.
    pub name: String,
    /// Type.
    pub ty: ValueType,
    /// Initial value.
    pub init: Value,
}

/// A named position.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Fix {
    /// Identifier used by legs.
    pub id: String,
    /// Position.
    pub pos: GeoPoint,
    /// Altitude, metres in the plan's reference; `None` inherits.
    pub alt: Option<f64>,
}

/// One node of a stage: a leg, a pattern or a control construct, with a stable id.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Node {
    /// Stable id: the `id` attribute, or the position in the tree (`mission.3.1`).
    pub id: String,
    /// Line of the element in the source (1-based; 0 when built in code).
    pub line: u32,
    /// Column of the element in the source (1-based).
    pub col: u32,
    /// What the node is.
    pub kind: NodeKind,
    /// The element it was built from, so a leg's parameters can be modified in flight by
    /// attribute name and re-validated exactly as the parser would.
    #[serde(skip)]
    pub source: Option<Element>,
}

/// The kinds of nodes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "lowercase")]
pub enum NodeKind {
    /// IF, TF, DF, CF or RF.
    Path(PathLeg),
    /// HF, HA or HM.
    Hold(Hold),
    /// Boustrophedon area scan.
    Scan(Scan),
    /// Rings inside a polygon.
    Perimeter(Perimeter),
    /// Take-off.
    Takeoff(Takeoff),
    /// Landing.
    Landing(Landing),
    /// A loop.
    Iterative(Iterative),
    /// A choice.
    Alternative(Alternative),
}

impl NodeKind {
    /// The nested bodies of a control construct (empty for legs).
    pub fn bodies(&self) -> Vec<&Vec<Node>> {
        match self {
            NodeKind::Iterative(it) => vec![&it.body],
            NodeKind::Alternative(a) => a.branches.iter().map(|b| &b.body).collect(),
            _ => Vec::new(),
        }
    }
    /// Whether the node is a leg or pattern (produces waypoints itself).
    pub fn is_leaf(&self) -> bool {
        !matches!(self, NodeKind::Iterative(_) | NodeKind::Alternative(_))
    }
}

/// Altitude, speed and fly-over shared by every leg.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct LegCommon {
    /// `alt`: overrides the fix's altitude.
    pub alt: Option<f64>,
    /// `speed`, m/s.
    pub speed: Option<f64>,
    /// `flyOver`: pass over the fix rather than turn before it.
    pub fly_over: Option<bool>,
}

/// ARINC 424 path terminators that USAL's basic legs follow.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum PathKind {
    /// Initial fix.
    IF,
    /// Track to fix.
    TF,
    /// Direct to fix from the present position.
    DF,
    /// Course to fix.
    CF,
    /// Constant-radius arc to fix.
    RF,
}

/// Turn direction.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Turn {
    /// Right (clockwise seen from above).
    R,
    /// Left.
    L,
}

impl Turn {
    /// +1 for right, -1 for left.
    pub fn sign(self) -> f64 {
        match self {
            Turn::R => 1.0,
            Turn::L => -1.0,
        }
    }
}

/// A basic leg.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PathLeg {
    /// Path terminator.
    pub kind: PathKind,
    /// The fix the leg ends at.
    pub fix: Fix,
    /// CF: the course flown into the fix, degrees true.
    pub course: Option<f64>,
    /// CF: the length of the inbound course, metres.
    pub length: Option<f64>,
    /// RF: arc centre.
    pub center: Option<GeoPoint>,
    /// RF: turn direction.
    pub turn: Option<Turn>,
    /// Altitude, speed, fly-over.
    pub common: LegCommon,
}

/// The hold terminators.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum HoldKind {
    /// One circuit (or `circuits`), then exit.
    HF,
    /// Until the altitude is reached.
    HA,
    /// Until a condition or a command.
    HM,
}

/// Racetrack (aircraft) or rectangle (a rover turning on the spot, 003 §6.1.2).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum HoldShape {
    /// Two straight legs joined by semicircles.
    Racetrack,
    /// Four corners, all fly-over.
    Rectangle,
}

/// A holding pattern.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Hold {
    /// HF, HA or HM.
    pub kind: HoldKind,
    /// Holding fix.
    pub fix: Fix,
    /// Inbound course to the fix, degrees true.
    pub inbound_course: f64,
    /// Turn direction at the fix.
    pub turn: Turn,
    /// Straight-leg length, metres (`length`, or `time` × speed).
    pub length: Option<f64>,
    /// Straight-leg time, seconds.
    pub time: Option<f64>,
    /// Width, metres (default: twice the vehicle's turn radius).
    pub width: Option<f64>,
    /// Shape.
    pub shape: HoldShape,
    /// Number of circuits (HF default 1; HA/HM: an upper bound).
    pub circuits: Option<u32>,
    /// HM: exit condition.
    pub until: Option<Condition>,
    /// HA: target altitude (default the leg's altitude).
    pub target_alt: Option<f64>,
    /// HA: altitude tolerance, metres.
    pub alt_tolerance: f64,
    /// Altitude, speed, fly-over of the fix.
    pub common: LegCommon,
}

impl Hold {
    /// The width the hold is flown at by `v`: as given, else twice the turn radius but never
    /// below the minimum waypoint distance.
    pub fn flown_width(&self, v: &VehicleParams) -> f64 {
        self.width
            .unwrap_or_else(|| (2.0 * v.turn_radius).max(v.min_wp_distance))
    }
}

/// Which outer track a scan starts with, looking along the sweep bearing.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ScanEntry {
    /// The leftmost track first.
    Left,
    /// The rightmost track first.
    Right,
    /// Whichever end is nearest the previous waypoint.
    Nearest,
}

/// Which end the first track starts from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ScanStart {
    /// From the back of the area: the first track is flown along the sweep bearing.
    Back,
    /// From the front: the first track is flown against the sweep bearing.
    Front,
    /// Whichever is nearest the previous waypoint.
    Nearest,
}

/// A boustrophedon area scan.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Scan {
    /// The area, at least 3 vertices, not self-intersecting.
    pub polygon: Vec<GeoPoint>,
    /// Distance between tracks, metres.
    pub spacing: f64,
    /// Bearing of the tracks, degrees true; `None` chooses the one giving fewest tracks.
    pub sweep_angle: Option<f64>,
    /// First track.
    pub entry: ScanEntry,
    /// Starting end of the first track.
    pub start_side: ScanStart,
    /// Altitude and speed of the whole pattern.
    pub common: LegCommon,
}

/// Concentric rings inside a polygon.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Perimeter {
    /// The area.
    pub polygon: Vec<GeoPoint>,
    /// Distance between rings (the first is `spacing/2` inside the border), metres.
    pub spacing: f64,
    /// Number of rings.
    pub rings: u32,
    /// R flies clockwise, L anticlockwise.
    pub turn: Turn,
    /// Altitude and speed.
    pub common: LegCommon,
}

/// Take-off: climb at the fix to `clear_alt` above it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Takeoff {
    /// Runway or start fix.
    pub fix: Fix,
    /// Take-off heading, degrees true.
    pub heading: Option<f64>,
    /// Altitude above the fix at which the take-off is complete.
    pub clear_alt: f64,
}

/// Landing at a fix.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Landing {
    /// Touchdown fix.
    pub fix: Fix,
    /// Landing heading, degrees true.
    pub heading: Option<f64>,
}

/// How a loop ends.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LoopMode {
    /// A fixed number of passes (at least 1).
    Count(u32),
    /// Tested before each pass.
    While(Condition),
    /// Tested after each pass.
    Until(Condition),
}

/// `<iterative>`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Iterative {
    /// Termination.
    pub mode: LoopMode,
    /// The repeated nodes.
    pub body: Vec<Node>,
}

/// One branch of an `<alternative>`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Branch {
    /// `None` for `<otherwise>`.
    pub cond: Option<Condition>,
    /// The nodes flown when chosen.
    pub body: Vec<Node>,
}

/// `<alternative>`: the first branch whose condition holds at activation.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Alternative {
    /// `when` branches in order, then at most one `otherwise`.
    pub branches: Vec<Branch>,
}

/// What an emergency rule does.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "action", rename_all = "kebab-case")]
pub enum EmergencyAction {
    /// Continue with a stage.
    GotoStage {
        /// The stage.
        stage: Stage,
    },
    /// Continue with a leg.
    GotoLeg {
        /// The leg id.
        leg: String,
    },
    /// Hold at the present position until `exit_hold`.
    Hold,
    /// Go to the landing stage (or approach when there is no landing).
    Land,
}

/// `<emergency on=... action=...>`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct EmergencyRule {
    /// Name for the `emergency` command (default `rule<N>`).
    pub name: String,
    /// Fires when this becomes true.
    pub on: Condition,
    /// The reaction.
    pub action: EmergencyAction,
    /// Source line.
    pub line: u32,
}
