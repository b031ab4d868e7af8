//! XML flight plan → [`FlightPlan`], with validation errors that name the line, the column and
//! what is wrong. No I/O: the caller reads the file.

use crate::expr::{Condition, ExprError, Value, ValueType};
use crate::geo::GeoPoint;
use crate::model::*;
use crate::polygon::{auto_sweep, polygon_frame, self_intersection, width_across, MAX_VERTICES};
use crate::vehicle::{VehicleKind, VehicleParams};
use crate::xml::{parse_document, parse_elements, Attr, Element, Pos, XmlError};
use std::collections::{BTreeMap, BTreeSet};
use thiserror::Error;

/// A plan that cannot be loaded, with the position of the problem.
#[derive(Debug, Clone, PartialEq, Error)]
#[error("{line}:{col}: {kind}")]
pub struct PlanError {
    /// 1-based line (0 for nodes built in code).
    pub line: u32,
    /// 1-based column.
    pub col: u32,
    /// What is wrong.
    pub kind: PlanErrorKind,
}

/// What is wrong with a plan.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum PlanErrorKind {
    /// Not well-formed XML.
    #[error("{0}")]
    Xml(String),
    /// An element the format does not have here.
    #[error("unknown element <{name}> in <{parent}>")]
    UnknownElement {
        /// The element.
        name: String,
        /// Where it was found.
        parent: String,
    },
    /// An attribute the element does not have.
    #[error("unknown attribute `{name}` on <{element}>")]
    UnknownAttribute {
        /// The attribute.
        name: String,
        /// The element.
        element: String,
    },
    /// A required attribute is absent.
    #[error("<{element}> needs attribute `{name}`")]
    MissingAttribute {
        /// The attribute.
        name: String,
        /// The element.
        element: String,
    },
    /// A number that does not parse or is not finite.
    #[error("attribute `{name}`: `{value}` is not a number")]
    BadNumber {
        /// The attribute.
        name: String,
        /// Its text.
        value: String,
    },
    /// A value outside what the attribute accepts.
    #[error("attribute `{name}`: `{value}` {why}")]
    BadValue {
        /// The attribute.
        name: String,
        /// Its text.
        value: String,
        /// What is expected.
        why: String,
    },
    /// A leg refers to a fix that is not declared.
    #[error("unknown fix `{0}`")]
    UnknownFix(String),
    /// Two fixes with one id.
    #[error("fix `{0}` is declared twice")]
    DuplicateFix(String),
    /// Two nodes with one id.
    #[error("id `{0}` is used twice")]
    DuplicateId(String),
    /// Two variables with one name.
    #[error("variable `{0}` is declared twice (or shadows a built-in)")]
    DuplicateVariable(String),
    /// A polygon whose edges cross.
    #[error("the polygon self-intersects: edge {0} crosses edge {1} (edges numbered from 1)")]
    SelfIntersecting(usize, usize),
    /// A polygon with fewer than 3 vertices.
    #[error("a polygon needs at least 3 <pt> vertices, this one has {0}")]
    TooFewVertices(usize),
    /// Track spacing the vehicle cannot turn in.
    #[error(
        "spacing {spacing} m is below the vehicle's turn limit of {min} m (twice its turn radius)"
    )]
    SpacingBelowTurnLimit {
        /// Given spacing.
        spacing: f64,
        /// Smallest allowed.
        min: f64,
    },
    /// A dimension below the minimum waypoint distance.
    #[error("{what} {value} m is below the vehicle's minimum waypoint distance of {min} m")]
    BelowMinWaypointDistance {
        /// Which dimension.
        what: &'static str,
        /// Given value.
        value: f64,
        /// Smallest allowed.
        min: f64,
    },
    /// A racetrack narrower than the vehicle can turn.
    #[error(
        "hold width {width} m is below the vehicle's turn limit of {min} m (twice its turn radius)"
    )]
    HoldTooNarrow {
        /// Given width.
        width: f64,
        /// Smallest allowed.
        min: f64,
    },
    /// `count="0"`.
    #[error("iteration count must be at least 1")]
    ZeroIterations,
    /// A condition that does not parse or type-check.
    #[error(transparent)]
    Condition(#[from] ExprError),
    /// Misplaced, missing or repeated elements.
    #[error("{0}")]
    Structure(String),
    /// An emergency rule naming a leg that does not exist.
    #[error("unknown leg `{0}`")]
    UnknownLeg(String),
    /// The plan says it is for another kind of vehicle.
    #[error("the plan is written for vehicle `{plan}`, but this vehicle is `{vehicle}`")]
    WrongVehicle {
        /// The plan's `vehicle`.
        plan: VehicleKind,
        /// The vehicle it is loaded for.
        vehicle: VehicleKind,
    },
    /// A pattern bigger than the FPMa generates (the work and the memory grow with it).
    #[error("{what}: {value} is more than the {max} allowed")]
    TooLarge {
        /// What is counted.
        what: &'static str,
        /// How many the plan asks for.
        value: u64,
        /// The most allowed.
        max: u64,
    },
}

impl PlanError {
    fn at(pos: Pos, kind: PlanErrorKind) -> Self {
        Self {
            line: pos.line,
            col: pos.col,
            kind,
        }
    }
}

impl From<XmlError> for PlanError {
    fn from(e: XmlError) -> Self {
        PlanError::at(e.pos, PlanErrorKind::Xml(e.message))
    }
}

type Result<T> = std::result::Result<T, PlanError>;

/// Most tracks one scan may have.
pub const MAX_SCAN_TRACKS: u64 = 10_000;
/// Most rings one perimeter may have.
pub const MAX_RINGS: u32 = 1000;

/// Parses and validates a plan for `vehicle`.
///
/// # Errors
/// The first problem found, with its line and column.
pub fn parse_plan(src: &str, vehicle: &VehicleParams) -> Result<FlightPlan> {
    let root = parse_document(src)?;
    let plan = plan_from_element(&root)?;
    if let (Some(kind), Some(a)) = (plan.vehicle, root.attr("vehicle")) {
        if kind != vehicle.kind {
            return Err(PlanError::at(
                a.pos,
                PlanErrorKind::WrongVehicle {
                    plan: kind,
                    vehicle: vehicle.kind,
                },
            ));
        }
    }
    check_vehicle(&plan, vehicle)?;
    Ok(plan)
}

/// The vehicle kind a plan says it is written for (`<flightPlan vehicle="rover">`), read
/// without validating the rest; `None` when it says nothing or does not parse (then
/// [`parse_plan`] reports why).
pub fn declared_vehicle(src: &str) -> Option<VehicleKind> {
    let root = parse_document(src).ok()?;
    VehicleKind::from_name(&root.attr("vehicle")?.value)
}

fn plan_from_element(root: &Element) -> Result<FlightPlan> {
    if root.name != "flightPlan" {
        return Err(PlanError::at(
            root.pos,
            PlanErrorKind::Structure(format!(
                "the root element must be <flightPlan>, not <{}>",
                root.name
            )),
        ));
    }
    allow(
        root,
        &[
            "name",
            "version",
            "altRef",
            "defaultSpeed",
            "vehicle",
            "xmlns",
        ],
    )?;
    let vehicle = match root.attr("vehicle") {
        None => None,
        Some(a) => Some(
            VehicleKind::from_name(&a.value)
                .ok_or_else(|| bad_value(a, &a.value, "must be `rover` or `aircraft`"))?,
        ),
    };
    let mut plan = FlightPlan {
        name: root
            .attr("name")
            .map(|a| a.value.clone())
            .unwrap_or_default(),
        revision: opt_u32(root, "version")?,
        alt_ref: root
            .attr("altRef")
            .map_or_else(|| "MSL".to_string(), |a| a.value.clone()),
        default_speed: opt_pos_num(root, "defaultSpeed")?,
        vehicle,
        variables: Vec::new(),
        fixes: BTreeMap::new(),
        takeoff: Vec::new(),
        departure: Vec::new(),
        mission: Vec::new(),
        approach: Vec::new(),
        landing: Vec::new(),
        emergencies: Vec::new(),
    };
    const KNOWN: [&str; 9] = [
        "variables",
        "fixes",
        "takeoff",
        "departure",
        "mission",
        "approach",
        "landing",
        "emergency",
        "emergencies",
    ];
    let mut seen = BTreeSet::new();
    for c in &root.children {
        if !KNOWN.contains(&c.name.as_str()) {
            return Err(unknown_element(c, root));
        }
        if c.name != "emergency" && !seen.insert(c.name.as_str()) {
            return Err(PlanError::at(
                c.pos,
                PlanErrorKind::Structure(format!("<{}> appears twice", c.name)),
            ));
        }
    }
    // Declarations first, wherever they are in the document, so stages may use them.
    for c in root.children.iter().filter(|c| c.name == "variables") {
        allow(c, &[])?;
        for v in &c.children {
            if v.name != "var" {
                return Err(unknown_element(v, c));
            }
            allow(v, &["name", "type", "init"])?;
            let name = req(v, "name")?.value.clone();
            let ty_attr = req(v, "type")?;
            let ty = match ty_attr.value.as_str() {
                "bool" => ValueType::Bool,
                "number" => ValueType::Number,
                other => return Err(bad_value(ty_attr, other, "must be `bool` or `number`")),
            };
            let init = match v.attr("init") {
                Some(a) => Value::parse(ty, &a.value)
                    .ok_or_else(|| bad_value(a, &a.value, &format!("is not a {ty}")))?,
                None => match ty {
                    ValueType::Bool => Value::Bool(false),
                    ValueType::Number => Value::Number(0.0),
                },
            };
            if plan.var_type(&name).is_some() || !is_identifier(&name) {
                return Err(PlanError::at(v.pos, PlanErrorKind::DuplicateVariable(name)));
            }
            plan.variables.push(VarDecl { name, ty, init });
        }
    }
    for c in root.children.iter().filter(|c| c.name == "fixes") {
        allow(c, &[])?;
        for f in &c.children {
            if f.name != "fix" {
                return Err(unknown_element(f, c));
            }
            allow(f, &["id", "lat", "lon", "alt"])?;
            let id = req(f, "id")?.value.clone();
            let fix = Fix {
                id: id.clone(),
                pos: point(f)?,
                alt: opt_num(f, "alt")?,
            };
            if plan.fixes.insert(id.clone(), fix).is_some() {
                return Err(PlanError::at(f.pos, PlanErrorKind::DuplicateFix(id)));
            }
        }
    }
    let mut ids = BTreeSet::new();
    for c in &root.children {
        match c.name.as_str() {
            "takeoff" => {
                allow(c, &["id", "fix", "heading", "clearAlt"])?;
                no_children(c)?;
                let id = node_id(c, "takeoff", &mut ids)?;
                let kind = NodeKind::Takeoff(Takeoff {
                    fix: fix_ref(c, &plan)?,
                    heading: opt_num(c, "heading")?,
                    clear_alt: opt_num(c, "clearAlt")?.unwrap_or(10.0),
                });
                plan.takeoff = vec![node(c, id, kind)];
            }
            "landing" => {
                allow(c, &["id", "fix", "heading"])?;
                no_children(c)?;
                let id = node_id(c, "landing", &mut ids)?;
                let kind = NodeKind::Landing(Landing {
                    fix: fix_ref(c, &plan)?,
                    heading: opt_num(c, "heading")?,
                });
                plan.landing = vec![node(c, id, kind)];
            }
            "departure" | "mission" | "approach" => {
                allow(c, &[])?;
                let stage = Stage::from_name(&c.name).unwrap_or(Stage::Mission);
                let nodes = parse_nodes(&c.children, c, &plan, &mut ids, stage.name())?;
                *plan.stage_mut(stage) = nodes;
            }
            _ => {}
        }
    }
    let rule_elements: Vec<&Element> = root
        .children
        .iter()
        .flat_map(|c| match c.name.as_str() {
            "emergency" => vec![c],
            "emergencies" => c.children.iter().collect(),
            _ => Vec::new(),
        })
        .collect();
    for (i, e) in rule_elements.into_iter().enumerate() {
        if e.name != "emergency" {
            return Err(unknown_element(e, root));
        }
        let rule = emergency_rule(e, i, &plan)?;
        plan.emergencies.push(rule);
    }
    Ok(plan)
}

fn emergency_rule(e: &Element, i: usize, plan: &FlightPlan) -> Result<EmergencyRule> {
    allow(e, &["name", "on", "action", "stage", "leg"])?;
    no_children(e)?;
    let on = condition(req(e, "on")?, plan)?;
    let act = req(e, "action")?;
    let action = match act.value.as_str() {
        "goto-stage" => {
            let a = req(e, "stage")?;
            let stage = Stage::from_name(&a.value)
                .ok_or_else(|| bad_value(a, &a.value, "is not a stage name"))?;
            if plan.stage(stage).is_empty() {
                return Err(bad_value(
                    a,
                    &a.value,
                    "names a stage the plan does not have",
                ));
            }
            EmergencyAction::GotoStage { stage }
        }
        "goto-leg" => {
            let a = req(e, "leg")?;
            if plan.find(&a.value).is_none() {
                return Err(PlanError::at(
                    a.pos,
                    PlanErrorKind::UnknownLeg(a.value.clone()),
                ));
            }
            EmergencyAction::GotoLeg {
                leg: a.value.clone(),
            }
        }
        "hold" => EmergencyAction::Hold,
        "land" => EmergencyAction::Land,
        other => {
            return Err(bad_value(
                act,
                other,
                "must be goto-stage, goto-leg, hold or land",
            ))
        }
    };
    Ok(EmergencyRule {
        name: e
            .attr("name")
            .map_or_else(|| format!("rule{}", i + 1), |a| a.value.clone()),
        on,
        action,
        line: e.pos.line,
    })
}

/// Parses a fragment of leg elements (e.g. legs to insert in flight) against `plan`'s fixes and
/// variables, giving them ids under `prefix` unless they carry their own.
///
/// # Errors
/// As [`parse_plan`]; ids already used in `plan` are refused.
pub fn parse_fragment(
    src: &str,
    plan: &FlightPlan,
    vehicle: &VehicleParams,
    prefix: &str,
) -> Result<Vec<Node>> {
    let els = parse_elements(src)?;
    let mut ids = BTreeSet::new();
    collect_ids(plan, &mut ids);
    let parent = Element::new("fragment");
    let nodes = parse_nodes(&els, &parent, plan, &mut ids, prefix)?;
    for n in &nodes {
        check_node(n, vehicle)?;
    }
    Ok(nodes)
}

/// Re-parses a leaf node after changing some of its attributes, for in-flight modification.
///
/// # Errors
/// The changed leg is validated as if it had been written so.
pub fn modify_node(
    node: &Node,
    changes: &[(String, String)],
    plan: &FlightPlan,
    vehicle: &VehicleParams,
) -> Result<Node> {
    let pos = Pos {
        line: node.line,
        col: node.col,
    };
    let Some(mut el) = node.source.clone() else {
        return Err(PlanError::at(
            pos,
            PlanErrorKind::Structure(format!(
                "leg `{}` was not built from XML and cannot be modified",
                node.id
            )),
        ));
    };
    if !node.kind.is_leaf() {
        return Err(PlanError::at(
            pos,
            PlanErrorKind::Structure(format!(
                "`{}` is a control construct; only legs can be modified",
                node.id
            )),
        ));
    }
    for (k, v) in changes {
        if k == "id" || k == "type" {
            return Err(PlanError::at(
                pos,
                PlanErrorKind::Structure(format!("attribute `{k}` of a leg cannot be modified")),
            ));
        }
        el.set_attr(k, v);
    }
    let kind = leaf(&el, plan)?;
    let n = Node {
        id: node.id.clone(),
        line: node.line,
        col: node.col,
        kind,
        source: Some(el),
    };
    check_node(&n, vehicle)?;
    Ok(n)
}

fn collect_ids(plan: &FlightPlan, ids: &mut BTreeSet<String>) {
    fn walk(nodes: &[Node], ids: &mut BTreeSet<String>) {
        for n in nodes {
            ids.insert(n.id.clone());
            for b in n.kind.bodies() {
                walk(b, ids);
            }
        }
    }
    for s in Stage::ALL {
        walk(plan.stage(s), ids);
    }
}

fn parse_nodes(
    els: &[Element],
    parent: &Element,
    plan: &FlightPlan,
    ids: &mut BTreeSet<String>,
    prefix: &str,
) -> Result<Vec<Node>> {
    let mut out = Vec::new();
    for (i, el) in els.iter().enumerate() {
        let auto = format!("{prefix}.{}", i + 1);
        let id = node_id(el, &auto, ids)?;
        let kind = match el.name.as_str() {
            "leg" | "scan" | "perimeter" => leaf(el, plan)?,
            "iterative" => {
                allow(el, &["id", "count", "while", "until"])?;
                let given: Vec<&Attr> = ["count", "while", "until"]
                    .iter()
                    .filter_map(|k| el.attr(k))
                    .collect();
                if given.len() != 1 {
                    return Err(PlanError::at(
                        el.pos,
                        PlanErrorKind::Structure(
                            "<iterative> needs exactly one of `count`, `while`, `until`".into(),
                        ),
                    ));
                }
                let a = given[0];
                let mode = match a.name.as_str() {
                    "count" => {
                        let n = a
                            .value
                            .trim()
                            .parse::<u32>()
                            .map_err(|_| bad_value(a, &a.value, "is not a whole number"))?;
                        if n == 0 {
                            return Err(PlanError::at(a.pos, PlanErrorKind::ZeroIterations));
                        }
                        LoopMode::Count(n)
                    }
                    "while" => LoopMode::While(condition(a, plan)?),
                    _ => LoopMode::Until(condition(a, plan)?),
                };
                let body = parse_nodes(&el.children, el, plan, ids, &id)?;
                if body.is_empty() {
                    return Err(PlanError::at(
                        el.pos,
                        PlanErrorKind::Structure("<iterative> has no legs".into()),
                    ));
                }
                NodeKind::Iterative(Iterative { mode, body })
            }
            "alternative" => {
                allow(el, &["id"])?;
                let mut branches = Vec::new();
                for (k, b) in el.children.iter().enumerate() {
                    let bprefix = format!("{id}.{}", k + 1);
                    let cond = match b.name.as_str() {
                        "when" => {
                            allow(b, &["cond"])?;
                            Some(condition(req(b, "cond")?, plan)?)
                        }
                        "otherwise" => {
                            allow(b, &[])?;
                            if k + 1 != el.children.len() {
                                return Err(PlanError::at(
                                    b.pos,
                                    PlanErrorKind::Structure(
                                        "<otherwise> must be the last branch".into(),
                                    ),
                                ));
                            }
                            None
                        }
                        _ => return Err(unknown_element(b, el)),
                    };
                    let body = parse_nodes(&b.children, b, plan, ids, &bprefix)?;
                    branches.push(Branch { cond, body });
                }
                if branches.is_empty() {
                    return Err(PlanError::at(
                        el.pos,
                        PlanErrorKind::Structure("<alternative> needs at least one <when>".into()),
                    ));
                }
                NodeKind::Alternative(Alternative { branches })
            }
            _ => return Err(unknown_element(el, parent)),
        };
        let source = kind.is_leaf().then(|| el.clone());
        out.push(Node {
            id,
            line: el.pos.line,
            col: el.pos.col,
            kind,
            source,
        });
    }
    Ok(out)
}

fn leaf(el: &Element, plan: &FlightPlan) -> Result<NodeKind> {
    match el.name.as_str() {
        "scan" => {
            allow(
                el,
                &[
                    "id",
                    "alt",
                    "speed",
                    "spacing",
                    "sweepAngle",
                    "entry",
                    "startSide",
                ],
            )?;
            let polygon = polygon(el)?;
            let entry = match el.attr("entry") {
                None => ScanEntry::Nearest,
                Some(a) => match a.value.as_str() {
                    "left" => ScanEntry::Left,
                    "right" => ScanEntry::Right,
                    "nearest" => ScanEntry::Nearest,
                    v => return Err(bad_value(a, v, "must be left, right or nearest")),
                },
            };
            let start_side = match el.attr("startSide") {
                None => ScanStart::Nearest,
                Some(a) => match a.value.as_str() {
                    "back" => ScanStart::Back,
                    "front" => ScanStart::Front,
                    "nearest" => ScanStart::Nearest,
                    v => return Err(bad_value(a, v, "must be back, front or nearest")),
                },
            };
            Ok(NodeKind::Scan(Scan {
                polygon,
                spacing: req_pos_num(el, "spacing")?,
                sweep_angle: opt_num(el, "sweepAngle")?,
                entry,
                start_side,
                common: common(el, false)?,
            }))
        }
        "perimeter" => {
            allow(el, &["id", "alt", "speed", "spacing", "rings", "turn"])?;
            let rings = opt_u32(el, "rings")?.unwrap_or(1);
            let rings_pos = el.attr("rings").map_or(el.pos, |a| a.pos);
            if rings == 0 {
                return Err(PlanError::at(rings_pos, PlanErrorKind::ZeroIterations));
            }
            if rings > MAX_RINGS {
                return Err(PlanError::at(
                    rings_pos,
                    PlanErrorKind::TooLarge {
                        what: "perimeter rings",
                        value: u64::from(rings),
                        max: u64::from(MAX_RINGS),
                    },
                ));
            }
            Ok(NodeKind::Perimeter(Perimeter {
                polygon: polygon(el)?,
                spacing: req_pos_num(el, "spacing")?,
                rings,
                turn: turn(el)?.unwrap_or(Turn::R),
                common: common(el, false)?,
            }))
        }
        _ => {
            no_children(el)?;
            let ty = req(el, "type")?;
            let path = |kind: PathKind, extra: &[&str]| -> Result<NodeKind> {
                let mut allowed = vec!["id", "type", "fix", "alt", "speed", "flyOver"];
                allowed.extend_from_slice(extra);
                allow(el, &allowed)?;
                Ok(NodeKind::Path(PathLeg {
                    kind,
                    fix: fix_ref(el, plan)?,
                    course: opt_num(el, "course")?,
                    length: opt_pos_num(el, "length")?,
                    center: center(el, plan)?,
                    turn: turn(el)?,
                    common: common(el, true)?,
                }))
            };
            match ty.value.as_str() {
                "IF" => path(PathKind::IF, &[]),
                "TF" => path(PathKind::TF, &[]),
                "DF" => path(PathKind::DF, &[]),
                "CF" => {
                    req(el, "course")?;
                    path(PathKind::CF, &["course", "length"])
                }
                "RF" => {
                    req(el, "turn")?;
                    if el.attr("center").is_none() && el.attr("centerLat").is_none() {
                        return Err(PlanError::at(
                            el.pos,
                            PlanErrorKind::MissingAttribute {
                                name: "center".into(),
                                element: "leg type=\"RF\"".into(),
                            },
                        ));
                    }
                    path(PathKind::RF, &["center", "centerLat", "centerLon", "turn"])
                }
                "HF" | "HA" | "HM" => {
                    allow(
                        el,
                        &[
                            "id",
                            "type",
                            "fix",
                            "alt",
                            "speed",
                            "flyOver",
                            "inboundCourse",
                            "turn",
                            "length",
                            "time",
                            "width",
                            "shape",
                            "circuits",
                            "until",
                            "targetAlt",
                            "altTolerance",
                        ],
                    )?;
                    let kind = match ty.value.as_str() {
                        "HF" => HoldKind::HF,
                        "HA" => HoldKind::HA,
                        _ => HoldKind::HM,
                    };
                    if el.attr("length").is_none() && el.attr("time").is_none() {
                        return Err(PlanError::at(
                            el.pos,
                            PlanErrorKind::MissingAttribute {
                                name: "length` or `time".into(),
                                element: "leg".into(),
                            },
                        ));
                    }
                    let shape = match el.attr("shape") {
                        None => HoldShape::Racetrack,
                        Some(a) => match a.value.as_str() {
                            "racetrack" => HoldShape::Racetrack,
                            "rectangle" => HoldShape::Rectangle,
                            v => return Err(bad_value(a, v, "must be racetrack or rectangle")),
                        },
                    };
                    let circuits = opt_u32(el, "circuits")?;
                    if circuits == Some(0) {
                        return Err(PlanError::at(
                            el.attr("circuits").map_or(el.pos, |a| a.pos),
                            PlanErrorKind::ZeroIterations,
                        ));
                    }
                    let until = match el.attr("until") {
                        Some(a) if kind == HoldKind::HM => Some(condition(a, plan)?),
                        Some(a) => {
                            return Err(bad_value(a, &a.value, "is only allowed on an HM hold"))
                        }
                        None => None,
                    };
                    if kind != HoldKind::HA {
                        if let Some(a) = el.attr("targetAlt") {
                            return Err(bad_value(a, &a.value, "is only allowed on an HA hold"));
                        }
                    }
                    let fix = fix_ref(el, plan)?;
                    let common = common(el, true)?;
                    if kind == HoldKind::HA
                        && opt_num(el, "targetAlt")?
                            .or(common.alt)
                            .or(fix.alt)
                            .is_none()
                    {
                        return Err(PlanError::at(
                            el.pos,
                            PlanErrorKind::MissingAttribute {
                                name: "targetAlt".into(),
                                element: "leg type=\"HA\"".into(),
                            },
                        ));
                    }
                    Ok(NodeKind::Hold(Hold {
                        kind,
                        fix,
                        inbound_course: req_num(el, "inboundCourse")?,
                        turn: turn(el)?.unwrap_or(Turn::R),
                        length: opt_pos_num(el, "length")?,
                        time: opt_pos_num(el, "time")?,
                        width: opt_pos_num(el, "width")?,
                        shape,
                        circuits,
                        until,
                        target_alt: opt_num(el, "targetAlt")?,
                        alt_tolerance: opt_pos_num(el, "altTolerance")?.unwrap_or(5.0),
                        common,
                    }))
                }
                other => Err(bad_value(
                    ty,
                    other,
                    "is not a leg type (IF, TF, DF, CF, RF, HF, HA, HM)",
                )),
            }
        }
    }
}

/// Checks what depends on the vehicle: spacings and widths against its turn radius and minimum
/// waypoint distance.
///
/// # Errors
/// The first node that the vehicle cannot fly, with its position.
pub fn check_vehicle(plan: &FlightPlan, vehicle: &VehicleParams) -> Result<()> {
    if let Some(kind) = plan.vehicle.filter(|k| *k != vehicle.kind) {
        // A plan built in code (parse_plan names the attribute's position itself).
        return Err(PlanError {
            line: 0,
            col: 0,
            kind: PlanErrorKind::WrongVehicle {
                plan: kind,
                vehicle: vehicle.kind,
            },
        });
    }
    fn walk(nodes: &[Node], v: &VehicleParams) -> Result<()> {
        for n in nodes {
            check_node(n, v)?;
            for b in n.kind.bodies() {
                walk(b, v)?;
            }
        }
        Ok(())
    }
    for s in Stage::ALL {
        walk(plan.stage(s), vehicle)?;
    }
    Ok(())
}

fn check_node(n: &Node, v: &VehicleParams) -> Result<()> {
    let pos = Pos {
        line: n.line,
        col: n.col,
    };
    let err = |kind| Err(PlanError::at(pos, kind));
    match &n.kind {
        NodeKind::Scan(s) => {
            let frame = polygon_frame(&s.polygon);
            let local: Vec<_> = s.polygon.iter().map(|p| frame.to_local(*p)).collect();
            let bearing = s.sweep_angle.unwrap_or_else(|| auto_sweep(&local));
            let tracks = (width_across(&local, bearing) / s.spacing).ceil();
            if tracks > MAX_SCAN_TRACKS as f64 {
                return err(PlanErrorKind::TooLarge {
                    what: "scan tracks (the area's width / spacing)",
                    value: tracks as u64,
                    max: MAX_SCAN_TRACKS,
                });
            }
            if s.spacing < 2.0 * v.turn_radius {
                return err(PlanErrorKind::SpacingBelowTurnLimit {
                    spacing: s.spacing,
                    min: 2.0 * v.turn_radius,
                });
            }
            if s.spacing < v.min_wp_distance {
                return err(PlanErrorKind::BelowMinWaypointDistance {
                    what: "scan spacing",
                    value: s.spacing,
                    min: v.min_wp_distance,
                });
            }
        }
        NodeKind::Perimeter(p) if p.spacing < v.min_wp_distance => {
            return err(PlanErrorKind::BelowMinWaypointDistance {
                what: "perimeter spacing",
                value: p.spacing,
                min: v.min_wp_distance,
            });
        }
        NodeKind::Hold(h) => {
            let width = hold_width(h, v);
            if h.shape == HoldShape::Racetrack && width < 2.0 * v.turn_radius - 1e-9 {
                return err(PlanErrorKind::HoldTooNarrow {
                    width,
                    min: 2.0 * v.turn_radius,
                });
            }
            if width < v.min_wp_distance {
                return err(PlanErrorKind::BelowMinWaypointDistance {
                    what: "hold width",
                    value: width,
                    min: v.min_wp_distance,
                });
            }
            if let Some(len) = h.length {
                if len < v.min_wp_distance {
                    return err(PlanErrorKind::BelowMinWaypointDistance {
                        what: "hold length",
                        value: len,
                        min: v.min_wp_distance,
                    });
                }
            }
        }
        _ => {}
    }
    Ok(())
}

/// The width a hold is flown at: as given, else twice the turn radius but never below the
/// minimum waypoint distance.
pub fn hold_width(h: &Hold, v: &VehicleParams) -> f64 {
    h.width
        .unwrap_or_else(|| (2.0 * v.turn_radius).max(v.min_wp_distance))
}

fn node(el: &Element, id: String, kind: NodeKind) -> Node {
    Node {
        id,
        line: el.pos.line,
        col: el.pos.col,
        kind,
        source: Some(el.clone()),
    }
}

fn node_id(el: &Element, auto: &str, ids: &mut BTreeSet<String>) -> Result<String> {
    let (id, pos) = match el.attr("id") {
        Some(a) => (a.value.clone(), a.pos),
        None => (auto.to_string(), el.pos),
    };
    if id.is_empty() {
        return Err(PlanError::at(
            pos,
            PlanErrorKind::Structure("an id cannot be empty".into()),
        ));
    }
    if !ids.insert(id.clone()) {
        return Err(PlanError::at(pos, PlanErrorKind::DuplicateId(id)));
    }
    Ok(id)
}

fn is_identifier(s: &str) -> bool {
    let mut c = s.chars();
    c.next().is_some_and(|f| f.is_alphabetic() || f == '_')
        && c.all(|ch| ch.is_alphanumeric() || ch == '_' || ch == '.')
        && !matches!(s, "and" | "or" | "not" | "true" | "false")
}

fn unknown_element(el: &Element, parent: &Element) -> PlanError {
    PlanError::at(
        el.pos,
        PlanErrorKind::UnknownElement {
            name: el.name.clone(),
            parent: parent.name.clone(),
        },
    )
}

fn allow(el: &Element, allowed: &[&str]) -> Result<()> {
    for a in &el.attrs {
        if !allowed.contains(&a.name.as_str()) {
            return Err(PlanError::at(
                a.pos,
                PlanErrorKind::UnknownAttribute {
                    name: a.name.clone(),
                    element: el.name.clone(),
                },
            ));
        }
    }
    Ok(())
}

fn no_children(el: &Element) -> Result<()> {
    match el.children.first() {
        Some(c) => Err(unknown_element(c, el)),
        None => Ok(()),
    }
}

fn req<'a>(el: &'a Element, name: &str) -> Result<&'a Attr> {
    el.attr(name).ok_or_else(|| {
        PlanError::at(
            el.pos,
            PlanErrorKind::MissingAttribute {
                name: name.into(),
                element: el.name.clone(),
            },
        )
    })
}

fn bad_value(a: &Attr, v: &str, why: &str) -> PlanError {
    PlanError::at(
        a.pos,
        PlanErrorKind::BadValue {
            name: a.name.clone(),
            value: v.to_string(),
            why: why.to_string(),
        },
    )
}

fn number(a: &Attr) -> Result<f64> {
    a.value
        .trim()
        .parse::<f64>()
        .ok()
        .filter(|v| v.is_finite())
        .ok_or_else(|| {
            PlanError::at(
                a.pos,
                PlanErrorKind::BadNumber {
                    name: a.name.clone(),
                    value: a.value.clone(),
                },
            )
        })
}

fn opt_num(el: &Element, name: &str) -> Result<Option<f64>> {
    el.attr(name).map(number).transpose()
}

fn req_num(el: &Element, name: &str) -> Result<f64> {
    number(req(el, name)?)
}

fn opt_pos_num(el: &Element, name: &str) -> Result<Option<f64>> {
    match el.attr(name) {
        None => Ok(None),
        Some(a) => {
            let v = number(a)?;
            if v <= 0.0 {
                return Err(bad_value(a, &a.value, "must be greater than zero"));
            }
            Ok(Some(v))
        }
    }
}

fn req_pos_num(el: &Element, name: &str) -> Result<f64> {
    req(el, name)?;
    opt_pos_num(el, name).map(|v| v.unwrap_or_default())
}

fn opt_u32(el: &Element, name: &str) -> Result<Option<u32>> {
    el.attr(name)
        .map(|a| {
            a.value
                .trim()
                .parse::<u32>()
                .map_err(|_| bad_value(a, &a.value, "is not a whole number"))
        })
        .transpose()
}

fn opt_bool(el: &Element, name: &str) -> Result<Option<bool>> {
    el.attr(name)
        .map(|a| match a.value.trim() {
            "true" | "1" | "yes" => Ok(true),
            "false" | "0" | "no" => Ok(false),
            v => Err(bad_value(a, v, "must be true or false")),
        })
        .transpose()
}

fn lat_lon(el: &Element, lat: &str, lon: &str) -> Result<GeoPoint> {
    let la = req(el, lat)?;
    let lo = req(el, lon)?;
    let (y, x) = (number(la)?, number(lo)?);
    if !(-90.0..=90.0).contains(&y) {
        return Err(bad_value(la, &la.value, "is not a latitude (-90..90)"));
    }
    if !(-180.0..=180.0).contains(&x) {
        return Err(bad_value(lo, &lo.value, "is not a longitude (-180..180)"));
    }
    Ok(GeoPoint::new(y, x))
}

fn point(el: &Element) -> Result<GeoPoint> {
    lat_lon(el, "lat", "lon")
}

fn fix_ref(el: &Element, plan: &FlightPlan) -> Result<Fix> {
    let a = req(el, "fix")?;
    plan.fixes
        .get(&a.value)
        .cloned()
        .ok_or_else(|| PlanError::at(a.pos, PlanErrorKind::UnknownFix(a.value.clone())))
}

fn center(el: &Element, plan: &FlightPlan) -> Result<Option<GeoPoint>> {
    if let Some(a) = el.attr("center") {
        return plan
            .fixes
            .get(&a.value)
            .map(|f| Some(f.pos))
            .ok_or_else(|| PlanError::at(a.pos, PlanErrorKind::UnknownFix(a.value.clone())));
    }
    if el.attr("centerLat").is_some() || el.attr("centerLon").is_some() {
        return lat_lon(el, "centerLat", "centerLon").map(Some);
    }
    Ok(None)
}

fn turn(el: &Element) -> Result<Option<Turn>> {
    el.attr("turn")
        .map(|a| match a.value.as_str() {
            "R" | "r" | "right" => Ok(Turn::R),
            "L" | "l" | "left" => Ok(Turn::L),
            v => Err(bad_value(a, v, "must be R or L")),
        })
        .transpose()
}

fn common(el: &Element, with_fly_over: bool) -> Result<LegCommon> {
    Ok(LegCommon {
        alt: opt_num(el, "alt")?,
        speed: opt_pos_num(el, "speed")?,
        fly_over: if with_fly_over {
            opt_bool(el, "flyOver")?
        } else {
            None
        },
    })
}

fn polygon(el: &Element) -> Result<Vec<GeoPoint>> {
    let mut pts = Vec::new();
    for c in &el.children {
        if c.name != "pt" {
            return Err(unknown_element(c, el));
        }
        allow(c, &["lat", "lon"])?;
        pts.push(point(c)?);
    }
    if pts.len() > MAX_VERTICES {
        return Err(PlanError::at(
            el.pos,
            PlanErrorKind::TooLarge {
                what: "polygon vertices",
                value: pts.len() as u64,
                max: MAX_VERTICES as u64,
            },
        ));
    }
    if pts.len() < 3 {
        return Err(PlanError::at(
            el.pos,
            PlanErrorKind::TooFewVertices(pts.len()),
        ));
    }
    let frame = polygon_frame(&pts);
    let local: Vec<_> = pts.iter().map(|p| frame.to_local(*p)).collect();
    for i in 0..local.len() {
        if local[i].minus(local[(i + 1) % local.len()]).norm() < 1e-3 {
            return Err(PlanError::at(
                el.children[(i + 1) % local.len()].pos,
                PlanErrorKind::Structure("a polygon vertex repeats the previous one".into()),
            ));
        }
    }
    if let Some((a, b)) = self_intersection(&local) {
        return Err(PlanError::at(
            el.pos,
            PlanErrorKind::SelfIntersecting(a + 1, b + 1),
        ));
    }
    Ok(pts)
}

fn condition(a: &Attr, plan: &FlightPlan) -> Result<Condition> {
    let at = |e: ExprError| PlanError::at(a.pos, PlanErrorKind::Condition(e));
    let c = Condition::parse(&a.value).map_err(at)?;
    match c.expr.check(&|n| plan.var_type(n)).map_err(at)? {
        ValueType::Bool => Ok(c),
        ValueType::Number => Err(at(ExprError::NotBoolean)),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const GOOD: &str = r#"<?xml version="1.0"?>
<flightPlan name="t" defaultSpeed="3">
  <variables><var name="go" type="bool" init="false"/><var name="n" type="number" init="2"/></variables>
  <fixes>
    <fix id="A" lat="41.275" lon="1.987" alt="0"/>
    <fix id="B" lat="41.2755" lon="1.9875"/>
  </fixes>
  <mission>
    <leg type="IF" fix="A"/>
    <leg id="toB" type="TF" fix="B" speed="2.5"/>
    <iterative count="2"><leg type="TF" fix="A"/><leg type="TF" fix="B"/></iterative>
    <alternative>
      <when cond="go and n &gt; 1"><leg type="DF" fix="A"/></when>
      <otherwise><leg type="HM" fix="A" inboundCourse="90" length="20" width="10" until="go"/></otherwise>
    </alternative>
  </mission>
  <emergency on="n &lt; 0" action="goto-stage" stage="mission"/>
</flightPlan>"#;

    fn parse(src: &str) -> Result<FlightPlan> {
        parse_plan(src, &VehicleParams::rover())
    }

    fn err_of(src: &str) -> PlanError {
        parse(src).expect_err("the plan should be refused")
    }

    fn with_mission(body: &str) -> String {
        GOOD.replacen(
            &GOOD[GOOD.find("<mission>").unwrap()..GOOD.find("</mission>").unwrap()],
            &format!("<mission>\n{body}\n"),
            1,
        )
    }

    #[test]
    fn parses_the_model() {
        let p = parse(GOOD).unwrap();
        assert_eq!(p.fixes.len(), 2);
        assert_eq!(p.mission.len(), 4);
        assert_eq!(p.mission[1].id, "toB");
        assert_eq!(p.mission[2].id, "mission.3");
        let NodeKind::Iterative(it) = &p.mission[2].kind else {
            panic!()
        };
        assert_eq!(it.mode, LoopMode::Count(2));
        assert_eq!(it.body[1].id, "mission.3.2");
        let NodeKind::Alternative(alt) = &p.mission[3].kind else {
            panic!()
        };
        assert_eq!(alt.branches.len(), 2);
        assert_eq!(alt.branches[1].body[0].id, "mission.4.2.1");
        assert_eq!(p.emergencies.len(), 1);
        assert_eq!(p.mission[1].line, 10);
    }

    #[test]
    fn unknown_fix_names_line_and_fix() {
        let e = err_of(&with_mission(r#"<leg type="TF" fix="NOPE"/>"#));
        assert_eq!(e.line, 9);
        assert_eq!(e.kind, PlanErrorKind::UnknownFix("NOPE".into()));
        assert!(e.to_string().starts_with("9:16: unknown fix"), "{e}");
    }

    #[test]
    fn unknown_element_and_attribute() {
        let e = err_of(&with_mission(r#"  <leg type="TF" fix="A" colour="red"/>"#));
        assert_eq!((e.line, e.col), (9, 26));
        assert!(matches!(e.kind, PlanErrorKind::UnknownAttribute { .. }));
        let e = err_of(&with_mission("<loop/>"));
        assert_eq!(e.line, 9);
        assert!(matches!(e.kind, PlanErrorKind::UnknownElement { .. }));
    }

    #[test]
    fn bad_number_and_zero_count() {
        let e = err_of(&with_mission(r#"<leg type="TF" fix="A" speed="fast"/>"#));
        assert!(matches!(e.kind, PlanErrorKind::BadNumber { .. }), "{e}");
        let e = err_of(&with_mission(
            "\n<iterative count=\"0\"><leg type=\"TF\" fix=\"A\"/></iterative>",
        ));
        assert_eq!(e.line, 10);
        assert_eq!(e.kind, PlanErrorKind::ZeroIterations);
    }

    #[test]
    fn self_intersecting_polygon() {
        let e = err_of(&with_mission(
            r#"<scan spacing="5">
<pt lat="41.2750" lon="1.9870"/><pt lat="41.2760" lon="1.9880"/>
<pt lat="41.2750" lon="1.9880"/><pt lat="41.2760" lon="1.9870"/></scan>"#,
        ));
        assert_eq!(e.line, 9);
        assert_eq!(e.kind, PlanErrorKind::SelfIntersecting(1, 3));
    }

    #[test]
    fn spacing_below_turn_limit_for_an_aircraft() {
        let src = with_mission(
            r#"<scan spacing="100">
<pt lat="41.27" lon="1.98"/><pt lat="41.28" lon="1.98"/><pt lat="41.28" lon="1.99"/></scan>"#,
        );
        let e = parse_plan(&src, &VehicleParams::aircraft()).unwrap_err();
        assert!(
            matches!(e.kind, PlanErrorKind::SpacingBelowTurnLimit { .. }),
            "{e}"
        );
        assert_eq!(e.line, 9);
        parse(&src).unwrap();
    }

    #[test]
    fn conditions_are_type_checked() {
        let e = err_of(&with_mission(
            r#"<iterative until="n"><leg type="TF" fix="A"/></iterative>"#,
        ));
        assert_eq!(e.kind, PlanErrorKind::Condition(ExprError::NotBoolean));
        let e = err_of(&with_mission(
            r#"<iterative while="ghost &gt; 2"><leg type="TF" fix="A"/></iterative>"#,
        ));
        assert_eq!(
            e.kind,
            PlanErrorKind::Condition(ExprError::UnknownVariable("ghost".into()))
        );
    }

    #[test]
    fn malformed_xml_names_the_line() {
        let src = GOOD.replace(
            "<leg id=\"toB\" type=\"TF\" fix=\"B\" speed=\"2.5\"/>",
            "<leg id=\"toB\" type=\"TF\"",
        );
        let e = err_of(&src);
        assert!(matches!(e.kind, PlanErrorKind::Xml(_)), "{e}");
        assert!((10..=12).contains(&e.line), "{e}");
    }

    #[test]
    fn duplicate_ids_and_fixes() {
        let e = err_of(&with_mission(
            r#"<leg id="x" type="TF" fix="A"/><leg id="x" type="TF" fix="B"/>"#,
        ));
        assert_eq!(e.kind, PlanErrorKind::DuplicateId("x".into()));
        let e = err_of(&GOOD.replace(r#"<fix id="B""#, r#"<fix id="A""#));
        assert_eq!(e.kind, PlanErrorKind::DuplicateFix("A".into()));
    }

    #[test]
    fn modify_node_revalidates() {
        let p = parse(GOOD).unwrap();
        let n = &p.mission[1];
        let m = modify_node(
            n,
            &[("speed".into(), "4".into())],
            &p,
            &VehicleParams::rover(),
        )
        .unwrap();
        let NodeKind::Path(leg) = &m.kind else {
            panic!()
        };
        assert_eq!(leg.common.speed, Some(4.0));
        let e = modify_node(
            n,
            &[("speed".into(), "x".into())],
            &p,
            &VehicleParams::rover(),
        )
        .unwrap_err();
        assert!(matches!(e.kind, PlanErrorKind::BadNumber { .. }));
    }

    /// Every kind of refusal names the line of the element (or attribute) at fault and says
    /// what is wrong. The body goes on line 9 of the plan.
    #[test]
    fn every_validation_error_names_its_line_and_what() {
        const TRI: &str = r#"<pt lat="41.27" lon="1.98"/><pt lat="41.28" lon="1.98"/><pt lat="41.28" lon="1.99"/>"#;
        let aircraft = VehicleParams::aircraft();
        let rover = VehicleParams::rover();
        let many: String = (0..1001)
            .map(|i| {
                let a = f64::from(i) / 1001.0 * std::f64::consts::TAU;
                format!(
                    r#"<pt lat="{}" lon="{}"/>"#,
                    41.0 + 0.01 * a.sin(),
                    2.0 + 0.01 * a.cos()
                )
            })
            .collect();
        let cases: Vec<(String, &VehicleParams, &str)> = vec![
            (r#"<leg type="TF" fix="NOPE"/>"#.into(), &rover, "unknown fix `NOPE`"),
            (r#"<leg type="XX" fix="A"/>"#.into(), &rover, "is not a leg type"),
            (r#"<leg type="CF" fix="A"/>"#.into(), &rover, "needs attribute `course`"),
            (r#"<leg type="RF" fix="A" turn="R"/>"#.into(), &rover, "needs attribute `center`"),
            (r#"<leg type="HF" fix="A" inboundCourse="0"/>"#.into(), &rover, "`length` or `time`"),
            (r#"<leg type="HA" fix="B" inboundCourse="0" length="20"/>"#.into(), &rover, "targetAlt"),
            (r#"<leg type="HF" fix="A" inboundCourse="0" length="200" width="50"/>"#.into(), &aircraft, "hold width 50 m is below the vehicle's turn limit"),
            (r#"<leg type="HF" fix="A" inboundCourse="0" length="2" width="10"/>"#.into(), &rover, "hold length 2 m is below the vehicle's minimum waypoint distance"),
            (r#"<leg type="HF" fix="A" inboundCourse="0" length="20" circuits="0"/>"#.into(), &rover, "at least 1"),
            (r#"<leg type="HF" fix="A" inboundCourse="0" length="20" until="n &gt; 1"/>"#.into(), &rover, "only allowed on an HM"),
            (r#"<iterative count="0"><leg type="TF" fix="A"/></iterative>"#.into(), &rover, "iteration count must be at least 1"),
            (r#"<iterative count="2" until="go"><leg type="TF" fix="A"/></iterative>"#.into(), &rover, "exactly one of"),
            ("<iterative count=\"2\"></iterative>".into(), &rover, "has no legs"),
            (r#"<alternative><otherwise/><when cond="go"/></alternative>"#.into(), &rover, "must be the last"),
            (r#"<iterative until="n +"><leg type="TF" fix="A"/></iterative>"#.into(), &rover, "condition"),
            (format!(r#"<scan spacing="100">{TRI}</scan>"#), &aircraft, "spacing 100 m is below the vehicle's turn limit of 120 m"),
            (format!(r#"<scan spacing="3">{TRI}</scan>"#), &rover, "below the vehicle's minimum waypoint distance"),
            (r#"<scan spacing="5"><pt lat="41.27" lon="1.98"/><pt lat="41.28" lon="1.98"/></scan>"#.into(), &rover, "at least 3 <pt>"),
            (r#"<scan spacing="5"><pt lat="41.27" lon="1.98"/><pt lat="41.28" lon="1.99"/><pt lat="41.27" lon="1.99"/><pt lat="41.28" lon="1.98"/></scan>"#.into(), &rover, "self-intersects"),
            (format!(r#"<scan spacing="5">{many}</scan>"#), &rover, "polygon vertices: 1001 is more than the 1000 allowed"),
            (r#"<scan spacing="5"><pt lat="41" lon="2"/><pt lat="42" lon="2"/><pt lat="42" lon="3"/><pt lat="41" lon="3"/></scan>"#.into(), &rover, "scan tracks (the area's width / spacing): 16"),
            (format!(r#"<perimeter spacing="5" rings="5000">{TRI}</perimeter>"#), &rover, "perimeter rings: 5000"),
            (r#"<leg type="TF" fix="A" speed="-1"/>"#.into(), &rover, "greater than zero"),
        ];
        for (body, vehicle, want) in cases {
            let e = parse_plan(&with_mission(&body), vehicle).expect_err(&body);
            assert_eq!(e.line, 9, "{body}: {e}");
            assert!(e.col > 0, "{body}: {e}");
            assert!(e.to_string().contains(want), "{body}: `{e}` lacks `{want}`");
        }
    }

    #[test]
    fn a_plan_for_another_vehicle_is_refused_at_its_attribute() {
        let src = GOOD.replace(
            "<flightPlan name=\"t\"",
            "<flightPlan vehicle=\"aircraft\" name=\"t\"",
        );
        let e = err_of(&src);
        assert_eq!((e.line, e.col), (2, 13), "{e}");
        assert_eq!(
            e.to_string(),
            "2:13: the plan is written for vehicle `aircraft`, but this vehicle is `rover`"
        );
        assert_eq!(declared_vehicle(&src), Some(VehicleKind::Aircraft));
        let e = err_of(&GOOD.replace("<flightPlan ", "<flightPlan vehicle=\"boat\" "));
        assert!(
            e.to_string().contains("must be `rover` or `aircraft`"),
            "{e}"
        );
        let ok = parse(&GOOD.replace("<flightPlan ", "<flightPlan vehicle=\"rover\" ")).unwrap();
        assert_eq!(ok.vehicle, Some(VehicleKind::Rover));
    }

    proptest! {
        #[test]
        fn parser_never_panics_on_random_input(s in "\\PC{0,200}") {
            let _ = parse(&s);
        }

        #[test]
        fn parser_never_panics_on_mangled_plans(cut in 0usize..2000, junk in "[<>/=\"a-zA-Z0-9 &;]{0,8}") {
            let mut s = GOOD.to_string();
            let mut at = cut.min(s.len());
            while !s.is_char_boundary(at) { at -= 1; }
            s.insert_str(at, &junk);
            let _ = parse(&s);
            let _ = parse(&s[..at]);
        }
    }
}
