//! Stage bodies: legs, patterns (scan, perimeter) and control constructs (iterative,
//! alternative) into [`Node`]s with stable ids; also fragments inserted and legs modified in
//! flight.

use super::attrs::*;
use super::error::{PlanError, PlanErrorKind, Result};
use super::MAX_RINGS;
use crate::geo::GeoPoint;
use crate::model::*;
use crate::polygon::{polygon_frame, self_intersection, MAX_VERTICES};
use crate::xml::{parse_elements, Attr, Element, Pos};
use std::collections::BTreeSet;

/// Parses a fragment of leg elements (e.g. legs to insert in flight) against `plan`'s fixes and
/// variables, giving them ids under `prefix` unless they carry their own.
///
/// # Errors
/// As [`parse_plan`]; ids already used in `plan` are refused.
pub fn parse_fragment(src: &str, plan: &FlightPlan, prefix: &str) -> Result<Vec<Node>> {
    let els = parse_elements(src)?;
    let mut ids = BTreeSet::new();
    collect_ids(plan, &mut ids);
    let parent = Element::new("fragment");
    parse_nodes(&els, &parent, plan, &mut ids, prefix)
}

/// Re-parses a leaf node after changing some of its attributes, for in-flight modification.
///
/// # Errors
/// The changed leg does not parse as written; what depends on the vehicle is checked with the
/// changed plan ([`crate::check::check_change`]).
pub fn modify_node(node: &Node, changes: &[(String, String)], plan: &FlightPlan) -> Result<Node> {
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
    Ok(Node {
        id: node.id.clone(),
        line: node.line,
        col: node.col,
        kind,
        source: Some(el),
    })
}

pub(super) fn collect_ids(plan: &FlightPlan, ids: &mut BTreeSet<String>) {
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

pub(super) fn parse_nodes(
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

pub(super) fn leaf(el: &Element, plan: &FlightPlan) -> Result<NodeKind> {
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
                        && opt_alt(el, "targetAlt")?
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
                        target_alt: opt_alt(el, "targetAlt")?,
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

pub(super) fn polygon(el: &Element) -> Result<Vec<GeoPoint>> {
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
