//! XML flight plan → [`FlightPlan`], with validation errors that name the line, the column and
//! what is wrong. No I/O: the caller reads the file.
//!
//! [`crate::xml`] reads the tree (positions from one line index, so parsing is linear in the
//! plan's size); `attrs` reads attribute values, `legs` the stage bodies, `error` says what is
//! wrong. This file reads the plan level: declarations, stages and emergency rules. The parser
//! knows no vehicle and flies nothing: [`crate::check`] does that, once per plan.

mod attrs;
mod error;
mod legs;

use attrs::*;
use error::Result;
pub use error::{PlanError, PlanErrorKind};
use legs::parse_nodes;
pub use legs::{modify_node, parse_fragment};

use crate::expr::{Value, ValueType};
use crate::model::*;
use crate::vehicle::VehicleKind;
use crate::xml::{parse_document, Element};
use std::collections::{BTreeMap, BTreeSet};

/// Most rings one perimeter may have.
pub const MAX_RINGS: u32 = 1000;

/// Parses a plan: its structure, names, values and polygons, all that holds whatever flies it.
/// What depends on the vehicle, the plan's end and its fence are [`crate::check`]'s.
///
/// # Errors
/// The first problem found, with its line and column.
pub fn parse_plan(src: &str) -> Result<FlightPlan> {
    plan_from_element(&parse_document(src)?)
}

/// The vehicle kind a plan says it is written for (`<flightPlan vehicle="rover">`), read from
/// the root's start tag alone (the plan is parsed once, by [`parse_plan`]); `None` when it
/// says nothing or the tag does not read (then [`parse_plan`] reports why).
pub fn declared_vehicle(src: &str) -> Option<VehicleKind> {
    let index = marea::xml::LineIndex::new(src);
    let mut reader = marea::xml::Reader::new(src, &index);
    loop {
        match reader.read_event().ok()? {
            marea::xml::XmlEvent::Start(root) => {
                let vehicle = root
                    .attributes()
                    .filter_map(|a| a.ok())
                    .find(|a| a.name == "vehicle")?;
                return VehicleKind::from_name(&vehicle.value().ok()?);
            }
            marea::xml::XmlEvent::Eof => return None,
            _ => {}
        }
    }
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
        Some(a) => Some(VehicleKind::from_name(&a.value).ok_or_else(|| {
            bad_value(a, &a.value, &format!("must be {}", VehicleKind::choices()))
        })?),
    };
    let mut plan = FlightPlan {
        name: root
            .attr("name")
            .map(|a| a.value.clone())
            .unwrap_or_default(),
        revision: opt_u32(root, "version")?,
        alt_ref: match root.attr("altRef") {
            None => "MSL".to_string(),
            Some(a) => {
                // Refused here rather than flown against the wrong reference.
                a.value.parse::<usal_types::AltRef>().map_err(|_| {
                    bad_value(a, &a.value, "must be `MSL`, `REL` (above home) or `AGL`")
                })?;
                a.value.clone()
            }
        },
        default_speed: opt_speed(root, "defaultSpeed")?,
        vehicle,
        vehicle_at: root
            .attr("vehicle")
            .map_or((0, 0), |a| (a.pos.line, a.pos.col)),
        variables: Vec::new(),
        fixes: BTreeMap::new(),
        takeoff: Vec::new(),
        departure: Vec::new(),
        mission: Vec::new(),
        approach: Vec::new(),
        landing: Vec::new(),
        emergencies: Vec::new(),
        fence: None,
    };
    const KNOWN: [&str; 10] = [
        "fence",
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
                alt: opt_alt(f, "alt")?,
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
                    clear_alt: opt_alt(c, "clearAlt")?.unwrap_or(10.0),
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
    if let Some(f) = root.children.iter().find(|c| c.name == "fence") {
        plan.fence = Some(fence_from(f)?);
    }
    Ok(plan)
}

/// Reads a `<fence maxDistance maxHeight homeLat homeLon action><pt lat lon/>...</fence>`
/// element: a plan's, or a vehicle's in a mission file (the same form). Its home stays unset
/// (`home_given` false) when it names none.
///
/// # Errors
/// What is wrong with the fence, at its position.
pub fn parse_fence(f: &Element) -> Result<PlanFence> {
    fence_from(f)
}

/// `<fence maxDistance maxHeight homeLat homeLon action><pt lat lon/>...</fence>`.
fn fence_from(f: &Element) -> Result<PlanFence> {
    allow(
        f,
        &["maxDistance", "maxHeight", "homeLat", "homeLon", "action"],
    )?;
    let home = match (f.attr("homeLat"), f.attr("homeLon")) {
        (None, None) => None,
        (Some(_), Some(_)) => {
            let p = lat_lon(f, "homeLat", "homeLon")?;
            Some((p.lat, p.lon))
        }
        _ => {
            return Err(PlanError::at(
                f.pos,
                PlanErrorKind::Structure(
                    "<fence> needs both homeLat and homeLon, or neither".into(),
                ),
            ))
        }
    };
    let action = match f.attr("action") {
        None => usal_types::FenceAction::default(),
        Some(a) => a
            .value
            .parse()
            .map_err(|_| bad_value(a, &a.value, "must be `report`, `rtl` or `hold`"))?,
    };
    let mut polygon = Vec::new();
    for c in &f.children {
        if c.name != "pt" {
            return Err(unknown_element(c, f));
        }
        allow(c, &["lat", "lon"])?;
        let p = point(c)?;
        polygon.push((p.lat, p.lon));
    }
    let fence = usal_types::Fence {
        home: home.unwrap_or_default(),
        max_distance_m: opt_pos_num(f, "maxDistance")?,
        max_height_m: opt_pos_num(f, "maxHeight")?,
        polygon,
        action,
    };
    if fence.is_empty() {
        return Err(PlanError::at(
            f.pos,
            PlanErrorKind::BadFence(
                "set maxDistance, maxHeight or at least 3 <pt> vertices".into(),
            ),
        ));
    }
    if fence.polygon.len() > crate::polygon::MAX_VERTICES {
        return Err(PlanError::at(
            f.pos,
            PlanErrorKind::TooLarge {
                what: "fence vertices",
                value: fence.polygon.len() as u64,
                max: crate::polygon::MAX_VERTICES as u64,
            },
        ));
    }
    if fence.polygon.len() >= 3 {
        let pts: Vec<crate::geo::GeoPoint> = fence
            .polygon
            .iter()
            .map(|&(lat, lon)| crate::geo::GeoPoint { lat, lon })
            .collect();
        let frame = crate::polygon::polygon_frame(&pts);
        let local: Vec<_> = pts.iter().map(|p| frame.to_local(*p)).collect();
        if let Some((a, b)) = crate::polygon::self_intersection(&local) {
            return Err(PlanError::at(
                f.pos,
                PlanErrorKind::SelfIntersecting(a + 1, b + 1),
            ));
        }
    }
    fence
        .validate()
        .map_err(|e| PlanError::at(f.pos, PlanErrorKind::BadFence(e)))?;
    Ok(PlanFence {
        fence,
        home_given: home.is_some(),
        line: f.pos.line,
        col: f.pos.col,
    })
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::expr::ExprError;
    use crate::vehicle::VehicleParams;
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
        parse_plan(src)
    }

    /// The refusal of a whole load (parse and check) for `vehicle`.
    fn refused(src: &str, vehicle: &VehicleParams) -> PlanError {
        match crate::check::load(src, vehicle) {
            Err(crate::check::CheckError::Plan(e)) => e,
            other => panic!("expected a refusal with a position, got {other:?}"),
        }
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
        let e = refused(&src, &VehicleParams::aircraft());
        assert!(
            matches!(e.kind, PlanErrorKind::SpacingBelowTurnLimit { .. }),
            "{e}"
        );
        assert_eq!(e.line, 9);
        crate::check::load(&src, &VehicleParams::rover()).unwrap();
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
        let m = modify_node(n, &[("speed".into(), "4".into())], &p).unwrap();
        let NodeKind::Path(leg) = &m.kind else {
            panic!()
        };
        assert_eq!(leg.common.speed, Some(4.0));
        let e = modify_node(n, &[("speed".into(), "x".into())], &p).unwrap_err();
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
            (r#"<leg type="TF" fix="A" speed="400"/>"#.into(), &rover, "faster than any vehicle flies a plan (at most 150 m/s)"),
            (r#"<leg type="TF" fix="A" alt="30000"/>"#.into(), &aircraft, "is not an altitude a vehicle flies (-500 to 20000 m)"),
            (r#"<leg type="HA" fix="A" inboundCourse="0" length="200" width="150" targetAlt="-900"/>"#.into(), &aircraft, "is not an altitude"),
        ];
        for (body, vehicle, want) in cases {
            let e = refused(&with_mission(&body), vehicle);
            assert_eq!(e.line, 9, "{body}: {e}");
            assert!(e.col > 0, "{body}: {e}");
            assert!(e.to_string().contains(want), "{body}: `{e}` lacks `{want}`");
        }
    }

    #[test]
    fn altitudes_and_speeds_out_of_any_vehicle_s_range_are_refused_where_written() {
        let e = err_of(&GOOD.replace(r#"defaultSpeed="3""#, r#"defaultSpeed="300""#));
        assert_eq!((e.line, e.col), (2, 22), "{e}");
        assert!(e.to_string().contains("at most 150 m/s"), "{e}");
        let e = err_of(&GOOD.replace(r#"lon="1.987" alt="0""#, r#"lon="1.987" alt="41000""#));
        assert_eq!(e.line, 5, "{e}");
        assert!(
            e.to_string().contains("`41000`") && e.to_string().contains("-500 to 20000 m"),
            "{e}"
        );
        // The edges are flyable.
        assert!(parse(&GOOD.replace(r#"alt="0""#, r#"alt="20000""#)).is_ok());
        assert!(parse(&GOOD.replace(r#"defaultSpeed="3""#, r#"defaultSpeed="150""#)).is_ok());
    }

    #[test]
    fn a_plan_for_another_vehicle_is_refused_at_its_attribute() {
        let src = GOOD.replace(
            "<flightPlan name=\"t\"",
            "<flightPlan vehicle=\"aircraft\" name=\"t\"",
        );
        let e = refused(&src, &VehicleParams::rover());
        assert_eq!((e.line, e.col), (2, 13), "{e}");
        assert_eq!(
            e.to_string(),
            "2:13: the plan is written for vehicle `aircraft`, but this vehicle is `rover`"
        );
        assert_eq!(declared_vehicle(&src), Some(VehicleKind::Aircraft));
        let e = err_of(&GOOD.replace("<flightPlan ", "<flightPlan vehicle=\"boat\" "));
        assert!(
            e.to_string()
                .contains("must be `rover`, `aircraft` or `copter`"),
            "{e}"
        );
        let ok = parse(&GOOD.replace("<flightPlan ", "<flightPlan vehicle=\"rover\" ")).unwrap();
        assert_eq!(ok.vehicle, Some(VehicleKind::Rover));
    }

    /// A plan of thousands of legs (read with one line index, not a rescan per element) still
    /// names the exact line and column of a problem near its end.
    #[test]
    fn a_large_plan_names_the_line_and_column_near_its_end() {
        use std::fmt::Write;
        const N: usize = 3000;
        let mut src = String::from("<flightPlan name=\"plà\">\n  <fixes>\n");
        for i in 0..N {
            let _ = writeln!(src, r#"    <fix id="F{i}" lat="41.{i:04}" lon="2"/>"#);
        }
        src.push_str("  </fixes>\n  <mission>\n");
        for i in 0..N {
            let _ = writeln!(src, r#"    <leg type="TF" fix="F{i}"/>"#);
        }
        let good = format!("{src}  </mission>\n</flightPlan>\n");
        assert_eq!(parse(&good).unwrap().mission.len(), N);
        // Lines: 2 header, N fixes, 2 more, N legs; the bad leg is the next one.
        let line = u32::try_from(2 * N + 5).unwrap();
        let bad =
            format!("{src}    <leg type=\"TF\" fix=\"NOPE\"/>\n  </mission>\n</flightPlan>\n");
        let e = err_of(&bad);
        assert_eq!((e.line, e.col), (line, 20), "{e}");
        assert_eq!(e.kind, PlanErrorKind::UnknownFix("NOPE".into()));
        let cut = format!("{src}    <leg type=\"TF\" fix=\"F1\"\n  </mission>\n</flightPlan>\n");
        let e = err_of(&cut);
        assert!(matches!(e.kind, PlanErrorKind::Xml(_)), "{e}");
        assert_eq!(e.line, line, "{e}");
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
