//! QGroundControl `.plan` import and export (FLIGHTPLAN "Interchange") for what the formats
//! share: waypoints (NAV_WAYPOINT), take-off, landing, speed changes, count loops (DO_JUMP) and
//! scans (survey complex items). What QGC cannot express — conditions, alternatives, holds that
//! wait, emergency rules — is refused with the reason rather than exported wrongly.
//!
//! Import goes through the XML format: the QGC items become an XML plan that is parsed and
//! validated like any other, so an imported plan is a plan like any other (modifiable legs,
//! line numbers in errors refer to the generated XML, which [`import`] also returns).

use crate::expand::{
    expand_landing, expand_path, expand_perimeter, expand_takeoff, hold_circuit, hold_entry, Ctx,
    Origin, Waypoint,
};
use crate::model::*;
use crate::parse::{parse_plan, PlanError};
use crate::polygon::polygon_frame;
use crate::vehicle::{VehicleKind, VehicleParams};
use serde_json::{json, Value as Json};
use std::fmt::Write;
use thiserror::Error;

const NAV_WAYPOINT: u64 = 16;
const NAV_LAND: u64 = 21;
const NAV_TAKEOFF: u64 = 22;
const DO_JUMP: u64 = 177;
const DO_CHANGE_SPEED: u64 = 178;
const DO_LAND_START: u64 = 189;

/// Why a plan cannot be exported to QGC.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum QgcExportError {
    /// A node QGC cannot represent.
    #[error("`{leg}` cannot be exported to QGroundControl: {why}")]
    Unrepresentable {
        /// The node (or rule) id.
        leg: String,
        /// Why.
        why: String,
    },
}

/// Why a QGC file cannot be imported.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum QgcImportError {
    /// Not JSON, or not a QGC plan.
    #[error("not a QGroundControl plan: {0}")]
    NotAPlan(String),
    /// An item this importer does not know.
    #[error("mission item {index}: {why}")]
    Item {
        /// 0-based position in `mission.items`.
        index: usize,
        /// What is wrong.
        why: String,
    },
    /// The converted plan does not validate.
    #[error("imported plan is invalid: {0}")]
    Invalid(#[from] PlanError),
}

#[derive(Clone)]
struct Exporter<'a> {
    vehicle: &'a VehicleParams,
    plan: &'a FlightPlan,
    items: Vec<Json>,
    prev: Option<Origin>,
    speed: Option<f64>,
    frame: u64,
}

impl Exporter<'_> {
    fn next_id(&self) -> u64 {
        self.items.len() as u64 + 1
    }
    fn ctx(&self) -> Ctx<'_> {
        Ctx {
            vehicle: self.vehicle,
            prev: self.prev,
            plan_speed: self.plan.default_speed,
        }
    }
    fn simple(&mut self, command: u64, params: [Json; 7], alt: f64) {
        let id = self.next_id();
        self.items.push(json!({
            "type": "SimpleItem", "autoContinue": true, "command": command, "doJumpId": id,
            "frame": self.frame, "params": params, "Altitude": alt, "AltitudeMode": 1,
            "AMSLAltAboveTerrain": null,
        }));
    }
    fn speed(&mut self, s: f64) {
        if self.speed != Some(s) {
            self.speed = Some(s);
            self.simple(
                DO_CHANGE_SPEED,
                [
                    json!(1),
                    json!(s),
                    json!(-1),
                    json!(0),
                    json!(0),
                    json!(0),
                    json!(0),
                ],
                0.0,
            );
        }
    }
    fn waypoints(&mut self, wps: &[Waypoint]) {
        for w in wps {
            self.speed(w.speed);
            let (cmd, p1) = match w.tag {
                crate::expand::WaypointTag::Takeoff => (NAV_TAKEOFF, 0.0),
                crate::expand::WaypointTag::Land => (NAV_LAND, 0.0),
                crate::expand::WaypointTag::Nav => (NAV_WAYPOINT, 0.0),
            };
            // NAV_WAYPOINT param3: 0 passes through the point (fly-over), > 0 passes by it.
            let pass = if w.fly_over || cmd != NAV_WAYPOINT {
                0.0
            } else {
                self.vehicle.turn_radius
            };
            self.simple(
                cmd,
                [
                    json!(p1),
                    json!(0),
                    json!(pass),
                    Json::Null,
                    json!(w.lat),
                    json!(w.lon),
                    json!(w.alt),
                ],
                w.alt,
            );
            self.prev = Some(Origin {
                pos: w.pos(),
                alt: w.alt,
                speed: w.speed,
            });
        }
    }
    fn refuse(leg: &str, why: &str) -> QgcExportError {
        QgcExportError::Unrepresentable {
            leg: leg.to_string(),
            why: why.to_string(),
        }
    }
    fn nodes(&mut self, nodes: &[Node]) -> Result<(), QgcExportError> {
        for n in nodes {
            let id = n.id.as_str();
            match &n.kind {
                NodeKind::Path(l) => {
                    let w = expand_path(l, id, &self.ctx());
                    self.waypoints(&w);
                }
                NodeKind::Takeoff(t) => {
                    let w = expand_takeoff(t, id, &self.ctx());
                    self.waypoints(&w);
                }
                NodeKind::Landing(l) => {
                    let w = expand_landing(l, id, &self.ctx());
                    self.waypoints(&w);
                }
                NodeKind::Hold(h) => {
                    if h.kind != HoldKind::HF {
                        return Err(Self::refuse(id, "a hold that waits for an altitude, a condition or a command has no QGC equivalent"));
                    }
                    let mut w = hold_entry(h, id, &self.ctx());
                    for _ in 0..h.circuits.unwrap_or(1) {
                        let c = hold_circuit(h, id, &self.ctx());
                        w.extend(c);
                    }
                    self.waypoints(&w);
                }
                NodeKind::Perimeter(p) => {
                    let w = expand_perimeter(p, id, &self.ctx());
                    self.waypoints(&w);
                }
                NodeKind::Scan(s) => self.survey(s, id),
                NodeKind::Iterative(it) => {
                    let LoopMode::Count(count) = it.mode else {
                        return Err(Self::refuse(
                            id,
                            "a loop ended by a condition cannot be exported without resolving it",
                        ));
                    };
                    let first = self.next_id();
                    let start = self.items.len();
                    // Each pass states its speed, since a jump back arrives with the last one.
                    self.speed = None;
                    self.nodes(&it.body)?;
                    if count > 1 && self.items.len() > start {
                        // A pass inherits speed and altitude from the one before, so the second
                        // pass can differ from the first (which inherits from before the loop).
                        // Then the first pass is written out on its own and the jump repeats
                        // the second, which every later pass equals.
                        let mut second = self.clone();
                        let second_first = second.next_id();
                        second.speed = None;
                        second.nodes(&it.body)?;
                        let (mut target, mut extra) = (first, count - 1);
                        if without_ids(&self.items[start..])
                            != without_ids(&second.items[start + (second_first - first) as usize..])
                        {
                            *self = second;
                            (target, extra) = (second_first, count - 2);
                        }
                        if extra > 0 {
                            // ArduPilot's DO_JUMP repeat count is the number of extra passes.
                            self.simple(
                                DO_JUMP,
                                [
                                    json!(target),
                                    json!(extra),
                                    json!(0),
                                    json!(0),
                                    json!(0),
                                    json!(0),
                                    json!(0),
                                ],
                                0.0,
                            );
                        }
                    }
                }
                NodeKind::Alternative(_) => {
                    return Err(Self::refuse(
                        id,
                        "alternatives choose by conditions, which QGC plans cannot express",
                    ));
                }
            }
        }
        Ok(())
    }
    fn survey(&mut self, s: &Scan, id: &str) {
        // Resolve `nearest` choices to the explicit ones the expansion made from here.
        let frame = polygon_frame(&s.polygon);
        let prev = self.prev.map(|o| frame.to_local(o.pos));
        let chosen = crate::expand::scan_tracks(s, &frame, prev);
        let mut resolved = (ScanEntry::Left, ScanStart::Back);
        for (e, st) in [
            (ScanEntry::Left, ScanStart::Back),
            (ScanEntry::Right, ScanStart::Back),
            (ScanEntry::Left, ScanStart::Front),
            (ScanEntry::Right, ScanStart::Front),
        ] {
            let trial = Scan {
                entry: e,
                start_side: st,
                ..s.clone()
            };
            if crate::expand::scan_tracks(&trial, &frame, prev) == chosen {
                resolved = (e, st);
                break;
            }
        }
        let explicit = Scan {
            entry: resolved.0,
            start_side: resolved.1,
            ..s.clone()
        };
        let wps = crate::expand::expand_scan(&explicit, id, &self.ctx());
        let entry_location = match resolved {
            (ScanEntry::Left, ScanStart::Back) => 0,
            (ScanEntry::Right, ScanStart::Back) => 1,
            (ScanEntry::Left, ScanStart::Front) => 2,
            _ => 3,
        };
        let pts: Vec<Xy> = s.polygon.iter().map(|p| frame.to_local(*p)).collect();
        let angle = s
            .sweep_angle
            .unwrap_or_else(|| crate::expand::auto_sweep(&pts));
        let alt = wps.first().map_or(0.0, |w| w.alt);
        let speed = wps.first().map_or(self.vehicle.default_speed, |w| w.speed);
        self.speed(speed);
        // The survey's own simple items, as QGC stores them, with the numbering continuing.
        let mut inner = Exporter {
            vehicle: self.vehicle,
            plan: self.plan,
            items: Vec::new(),
            prev: self.prev,
            speed: self.speed,
            frame: self.frame,
        };
        inner.waypoints(&wps);
        let inner_items = inner.items;
        let id_num = self.next_id();
        self.items.push(json!({
            "type": "ComplexItem", "complexItemType": "survey", "version": 5,
            "angle": angle, "entryLocation": entry_location,
            "flyAlternateTransects": false, "splitConcavePolygons": false,
            "polygon": s.polygon.iter().map(|p| json!([p.lat, p.lon])).collect::<Vec<_>>(),
            "TransectStyleComplexItem": {
                "version": 1, "TurnAroundDistance": 0, "Refly90Degrees": false,
                "CameraTriggerInTurnAround": true, "HoverAndCapture": false, "FollowTerrain": false,
                "CameraCalc": {
                    "version": 1, "CameraName": "Manual (no camera specs)",
                    "DistanceToSurface": alt, "DistanceToSurfaceRelative": true,
                    "AdjustedFootprintSide": s.spacing, "AdjustedFootprintFrontal": s.spacing,
                },
                "Items": inner_items,
                "VisualTransectPoints": wps.iter().map(|w| json!([w.lat, w.lon])).collect::<Vec<_>>(),
            },
            "doJumpId": id_num,
        }));
        self.prev = wps.last().map(|w| Origin {
            pos: w.pos(),
            alt: w.alt,
            speed: w.speed,
        });
    }
}

use crate::geo::Xy;

fn without_ids(items: &[Json]) -> Vec<Json> {
    items
        .iter()
        .map(|i| {
            let mut i = i.clone();
            if let Some(o) = i.as_object_mut() {
                o.remove("doJumpId");
            }
            i
        })
        .collect()
}

/// Exports a plan as a QGC `.plan` document.
///
/// # Errors
/// [`QgcExportError::Unrepresentable`] naming the first node (or rule) QGC cannot express.
pub fn export(plan: &FlightPlan, vehicle: &VehicleParams) -> Result<Json, QgcExportError> {
    if let Some(r) = plan.emergencies.first() {
        return Err(Exporter::refuse(
            &r.name,
            "emergency rules react to conditions, which QGC plans cannot express",
        ));
    }
    let mut ex = Exporter {
        vehicle,
        plan,
        items: Vec::new(),
        prev: None,
        speed: None,
        frame: if plan.alt_ref.eq_ignore_ascii_case("MSL") {
            0
        } else {
            3
        },
    };
    // A plan that lands marks where its landing sequence begins, as ArduPilot's missions do:
    // DO_LAND_START before the approach (or before the landing when there is none), where
    // RTL_AUTOLAND and MAV_CMD_DO_LAND_START jump to.
    let landing_begins = plan.landing_begins();
    for s in Stage::ALL {
        if Some(s) == landing_begins {
            let at = plan
                .stage(s)
                .first()
                .and_then(|n| match &n.kind {
                    NodeKind::Path(l) => Some(l.fix.pos),
                    NodeKind::Landing(l) => Some(l.fix.pos),
                    _ => None,
                })
                .map_or((0.0, 0.0), |p| (p.lat, p.lon));
            ex.simple(
                DO_LAND_START,
                [
                    json!(0),
                    json!(0),
                    json!(0),
                    json!(0),
                    json!(at.0),
                    json!(at.1),
                    json!(0),
                ],
                0.0,
            );
        }
        ex.nodes(plan.stage(s))?;
    }
    let items = ex.items;
    let home = plan
        .stage(
            Stage::ALL
                .into_iter()
                .find(|s| !plan.stage(*s).is_empty())
                .unwrap_or(Stage::Mission),
        )
        .first()
        .and_then(|n| match &n.kind {
            NodeKind::Path(l) => Some(&l.fix),
            NodeKind::Takeoff(t) => Some(&t.fix),
            _ => None,
        })
        .map_or(json!([0.0, 0.0, 0.0]), |f| {
            json!([f.pos.lat, f.pos.lon, f.alt.unwrap_or(0.0)])
        });
    Ok(json!({
        "fileType": "Plan", "version": 1, "groundStation": "QGroundControl",
        "geoFence": {"circles": [], "polygons": [], "version": 2},
        "rallyPoints": {"points": [], "version": 2},
        "mission": {
            "version": 2, "firmwareType": 3,
            "vehicleType": match vehicle.kind {
                VehicleKind::Rover => 10,
                VehicleKind::Aircraft => 1,
                VehicleKind::Copter => 2,
            },
            "cruiseSpeed": plan.default_speed.unwrap_or(vehicle.default_speed),
            "hoverSpeed": plan.default_speed.unwrap_or(vehicle.default_speed),
            "globalPlanAltitudeMode": 1,
            "plannedHomePosition": home,
            "items": items,
        },
    }))
}

fn num(v: &Json, index: usize, what: &str) -> Result<f64, QgcImportError> {
    v.as_f64()
        .filter(|x| x.is_finite())
        .ok_or_else(|| QgcImportError::Item {
            index,
            why: format!("{what} is missing or not a number"),
        })
}

/// Imports a QGC `.plan` document. Returns the plan, parsed (for [`crate::check`] to check for a
/// vehicle), and the XML it was converted to.
///
/// # Errors
/// Not a plan, an unsupported item, or XML that does not parse.
pub fn import(src: &str, name: &str) -> Result<(FlightPlan, String), QgcImportError> {
    let doc: Json =
        serde_json::from_str(src).map_err(|e| QgcImportError::NotAPlan(e.to_string()))?;
    if doc["fileType"] != "Plan" {
        return Err(QgcImportError::NotAPlan("fileType is not \"Plan\"".into()));
    }
    let items = doc["mission"]["items"]
        .as_array()
        .ok_or_else(|| QgcImportError::NotAPlan("no mission.items".into()))?;
    let frame = items.iter().find_map(|i| i["frame"].as_u64()).unwrap_or(3);
    // Each entry: (doJumpId of its first item, XML text).
    let mut nodes: Vec<(u64, String)> = Vec::new();
    let mut fixes = String::new();
    let (mut takeoff, mut landing) = (String::new(), String::new());
    let mut speed: Option<f64> = None;
    // The node index where a DO_LAND_START put the start of the approach.
    let mut approach_from: Option<usize> = None;
    // A jump may target the speed change that opens a loop body: it belongs to the next node.
    let mut pending: Option<u64> = None;
    let mut nfix = 0;
    let mut fix = |lat: f64, lon: f64, alt: f64, fixes: &mut String| {
        nfix += 1;
        let _ = writeln!(
            fixes,
            r#"    <fix id="WP{nfix}" lat="{lat}" lon="{lon}" alt="{alt}"/>"#
        );
        format!("WP{nfix}")
    };
    for (index, it) in items.iter().enumerate() {
        let own_id = it["doJumpId"].as_u64().unwrap_or(0);
        let jump_id = pending.unwrap_or(own_id);
        let is_speed = it["command"].as_u64() == Some(DO_CHANGE_SPEED);
        if !is_speed {
            pending = None;
        }
        match it["type"].as_str() {
            Some("SimpleItem") => {
                let p = &it["params"];
                let cmd = it["command"].as_u64().unwrap_or(0);
                match cmd {
                    NAV_WAYPOINT | NAV_TAKEOFF | NAV_LAND => {
                        let (lat, lon, alt) = (
                            num(&p[4], index, "latitude")?,
                            num(&p[5], index, "longitude")?,
                            num(&p[6], index, "altitude")?,
                        );
                        let id = fix(lat, lon, alt, &mut fixes);
                        match cmd {
                            NAV_TAKEOFF if nodes.is_empty() && takeoff.is_empty() => {
                                takeoff = format!(r#"  <takeoff fix="{id}" clearAlt="0"/>"#);
                            }
                            NAV_LAND if index + 1 == items.len() => {
                                landing = format!(r#"  <landing fix="{id}"/>"#);
                            }
                            NAV_WAYPOINT => {
                                let fly_over = p[2].as_f64().unwrap_or(0.0) == 0.0;
                                let sp = speed
                                    .map(|s| format!(r#" speed="{s}""#))
                                    .unwrap_or_default();
                                nodes.push((
                                    jump_id,
                                    format!(
                                        r#"<leg type="TF" fix="{id}" flyOver="{fly_over}"{sp}/>"#
                                    ),
                                ));
                            }
                            _ => {
                                return Err(QgcImportError::Item {
                                    index,
                                    why: "take-off and landing are supported only first and last"
                                        .into(),
                                })
                            }
                        }
                    }
                    DO_CHANGE_SPEED => {
                        speed = Some(num(&p[1], index, "speed")?);
                        pending.get_or_insert(own_id);
                    }
                    // Where the landing sequence begins: what follows is the approach.
                    DO_LAND_START if approach_from.is_none() => approach_from = Some(nodes.len()),
                    DO_LAND_START => {
                        return Err(QgcImportError::Item {
                            index,
                            why: "a second DO_LAND_START: a plan has one landing sequence".into(),
                        })
                    }
                    DO_JUMP => {
                        let target = p[0].as_f64().unwrap_or(0.0) as u64;
                        let repeat = p[1].as_f64().unwrap_or(0.0);
                        let start = nodes.iter().position(|(j, _)| *j == target).ok_or_else(|| QgcImportError::Item {
                            index,
                            why: format!("DO_JUMP to item {target}, which is not an earlier waypoint at this level"),
                        })?;
                        if repeat < 0.0 {
                            return Err(QgcImportError::Item {
                                index,
                                why: "DO_JUMP repeating forever (-1) has no plan equivalent".into(),
                            });
                        }
                        // A pass count must be a whole number an `<iterative count>` holds.
                        if repeat.fract() != 0.0 || repeat >= f64::from(u32::MAX) {
                            return Err(QgcImportError::Item {
                                index,
                                why: format!(
                                    "DO_JUMP repeat count {repeat} is not a whole number below {}",
                                    u32::MAX
                                ),
                            });
                        }
                        let body: Vec<String> = nodes.drain(start..).map(|(_, x)| x).collect();
                        nodes.push((
                            target,
                            format!(
                                "<iterative count=\"{}\">{}</iterative>",
                                repeat as u64 + 1,
                                body.join("")
                            ),
                        ));
                    }
                    other => {
                        return Err(QgcImportError::Item {
                            index,
                            why: format!("MAV_CMD {other} is not supported"),
                        })
                    }
                }
            }
            Some("ComplexItem") if it["complexItemType"] == "survey" => {
                let t = &it["TransectStyleComplexItem"];
                let cam = &t["CameraCalc"];
                let spacing = num(
                    &cam["AdjustedFootprintSide"],
                    index,
                    "CameraCalc.AdjustedFootprintSide",
                )?;
                let alt = num(
                    &cam["DistanceToSurface"],
                    index,
                    "CameraCalc.DistanceToSurface",
                )?;
                let angle = num(&it["angle"], index, "angle")?;
                let (entry, side) = match it["entryLocation"].as_u64().unwrap_or(0) {
                    0 => ("left", "back"),
                    1 => ("right", "back"),
                    2 => ("left", "front"),
                    _ => ("right", "front"),
                };
                let poly = it["polygon"]
                    .as_array()
                    .ok_or_else(|| QgcImportError::Item {
                        index,
                        why: "survey without polygon".into(),
                    })?;
                let mut pts = String::new();
                for v in poly {
                    let _ = write!(
                        pts,
                        r#"<pt lat="{}" lon="{}"/>"#,
                        num(&v[0], index, "polygon latitude")?,
                        num(&v[1], index, "polygon longitude")?
                    );
                }
                let sp = speed
                    .map(|s| format!(r#" speed="{s}""#))
                    .unwrap_or_default();
                nodes.push((
                    jump_id,
                    format!(r#"<scan alt="{alt}" spacing="{spacing}" sweepAngle="{angle}" entry="{entry}" startSide="{side}"{sp}>{pts}</scan>"#),
                ));
            }
            _ => {
                return Err(QgcImportError::Item {
                    index,
                    why: "only SimpleItem and survey ComplexItem are supported".into(),
                })
            }
        }
    }
    let alt_ref = if frame == 0 { "MSL" } else { "REL" };
    let name = name.replace(['"', '<', '>', '&'], "_");
    let lines = |nodes: &[(u64, String)]| -> String {
        nodes.iter().map(|(_, x)| format!("    {x}\n")).collect()
    };
    let split = approach_from.unwrap_or(nodes.len()).min(nodes.len());
    let body = lines(&nodes[..split]);
    let approach = if split < nodes.len() {
        format!("  <approach>\n{}  </approach>\n", lines(&nodes[split..]))
    } else {
        String::new()
    };
    let xml = format!(
        "<?xml version=\"1.0\" encoding=\"UTF-8\"?>\n<flightPlan name=\"{name}\" altRef=\"{alt_ref}\">\n  <fixes>\n{fixes}  </fixes>\n{takeoff}\n  <mission>\n{body}  </mission>\n{approach}{landing}\n</flightPlan>\n"
    );
    let plan = parse_plan(&xml)?;
    Ok((plan, xml))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::exec::expand_nominal;
    use crate::geo::distance;

    const PLAN: &str = r#"<flightPlan name="rt" altRef="REL" defaultSpeed="2">
  <fixes>
    <fix id="A" lat="41.27500" lon="1.98700" alt="0"/>
    <fix id="B" lat="41.27540" lon="1.98700" alt="0"/>
    <fix id="C" lat="41.27540" lon="1.98750" alt="0"/>
  </fixes>
  <mission>
    <leg type="IF" fix="A"/>
    <iterative count="3"><leg type="TF" fix="B"/><leg type="TF" fix="C" flyOver="true" speed="1.5"/></iterative>
    <scan spacing="8" sweepAngle="90" entry="right" startSide="front" alt="0">
      <pt lat="41.27560" lon="1.98700"/><pt lat="41.27590" lon="1.98700"/>
      <pt lat="41.27590" lon="1.98760"/><pt lat="41.27560" lon="1.98760"/></scan>
    <leg type="TF" fix="A" speed="2"/>
  </mission>
</flightPlan>"#;

    #[test]
    fn a_landing_plan_marks_its_approach_with_do_land_start_both_ways() {
        let v = VehicleParams::aircraft();
        let src = r#"<flightPlan name="circuit" altRef="MSL" defaultSpeed="20">
  <fixes>
    <fix id="STRIP" lat="41.27500" lon="1.98700" alt="0"/>
    <fix id="OUT" lat="41.28400" lon="1.98700" alt="150"/>
    <fix id="FAF" lat="41.27500" lon="2.00140" alt="80"/>
  </fixes>
  <takeoff fix="STRIP" clearAlt="60"/>
  <mission><leg type="TF" fix="OUT"/></mission>
  <approach><leg type="TF" fix="FAF" flyOver="true"/></approach>
  <landing fix="STRIP"/>
</flightPlan>"#;
        let plan = parse_plan(src).unwrap();
        let doc = export(&plan, &v).unwrap();
        let commands: Vec<u64> = doc["mission"]["items"]
            .as_array()
            .unwrap()
            .iter()
            .map(|i| i["command"].as_u64().unwrap())
            .filter(|c| *c != DO_CHANGE_SPEED)
            .collect();
        assert_eq!(
            commands,
            [
                NAV_TAKEOFF,
                NAV_WAYPOINT,
                DO_LAND_START,
                NAV_WAYPOINT,
                NAV_LAND
            ]
        );
        let (back, xml) = import(&doc.to_string(), "circuit").unwrap();
        assert_eq!(back.approach.len(), 1, "{xml}");
        assert_eq!(back.mission.len(), 1, "{xml}");
        let a = expand_nominal(plan, v.clone()).unwrap();
        let b = expand_nominal(back, v).unwrap();
        assert_eq!(a.len(), b.len(), "{xml}");
        for (x, y) in a.iter().zip(&b) {
            assert!(distance(x.pos(), y.pos()) < 0.01, "{x:?} vs {y:?}");
        }
        // One landing sequence only.
        let mut twice = doc.clone();
        let items = twice["mission"]["items"].as_array_mut().unwrap();
        let mark = items
            .iter()
            .find(|i| i["command"] == DO_LAND_START)
            .unwrap()
            .clone();
        items.insert(1, mark);
        let e = import(&twice.to_string(), "circuit").unwrap_err();
        assert!(e.to_string().contains("a second DO_LAND_START"), "{e}");
    }

    #[test]
    fn export_import_round_trip_keeps_the_waypoint_stream() {
        let v = VehicleParams::rover();
        let plan = parse_plan(PLAN).unwrap();
        let doc = export(&plan, &v).unwrap();
        let items = doc["mission"]["items"].as_array().unwrap();
        // The first pass enters at another speed than later ones, so it is written out and the
        // jump repeats the second pass once more.
        assert!(items
            .iter()
            .any(|i| i["command"] == DO_JUMP && i["params"][1] == 1));
        assert!(items.iter().any(|i| i["complexItemType"] == "survey"));
        let (back, xml) = import(&doc.to_string(), "rt").unwrap();
        assert!(xml.contains("<iterative count=\"2\">"), "{xml}");
        let a = expand_nominal(plan, v.clone()).unwrap();
        let b = expand_nominal(back, v).unwrap();
        assert_eq!(a.len(), b.len(), "{xml}");
        for (x, y) in a.iter().zip(&b) {
            assert!(distance(x.pos(), y.pos()) < 0.01, "{x:?} vs {y:?}");
            assert_eq!(
                (x.alt, x.speed, x.fly_over),
                (y.alt, y.speed, y.fly_over),
                "{x:?} vs {y:?}"
            );
        }
    }

    #[test]
    fn loop_with_equal_passes_is_one_jump() {
        let v = VehicleParams::rover();
        let src = PLAN.replace(
            r#"<leg type="TF" fix="B"/>"#,
            r#"<leg type="TF" fix="B" speed="2"/>"#,
        );
        let plan = parse_plan(&src).unwrap();
        let doc = export(&plan, &v).unwrap();
        let items = doc["mission"]["items"].as_array().unwrap();
        let jump = items.iter().find(|i| i["command"] == DO_JUMP).unwrap();
        assert_eq!(
            jump["params"][1], 2,
            "three passes: the body and two repeats"
        );
        // The jump goes back to the loop's first item, the speed change that opens the body.
        let target = items
            .iter()
            .find(|i| i["doJumpId"] == jump["params"][0])
            .unwrap();
        assert_eq!(target["command"], DO_CHANGE_SPEED);
        let (back, _) = import(&doc.to_string(), "rt").unwrap();
        assert_eq!(
            expand_nominal(plan, v.clone()).unwrap().len(),
            expand_nominal(back, v).unwrap().len()
        );
    }

    #[test]
    fn unrepresentable_nodes_are_refused_with_the_reason() {
        let v = VehicleParams::rover();
        let src = PLAN.replace(
            r#"<leg type="TF" fix="A" speed="2"/>"#,
            r#"<alternative id="alt"><when cond="true"><leg type="TF" fix="A"/></when></alternative>"#,
        );
        let e = export(&parse_plan(&src).unwrap(), &v).unwrap_err();
        assert!(
            e.to_string().contains("`alt`") && e.to_string().contains("conditions"),
            "{e}"
        );
        let src = PLAN.replace(
            r#"<iterative count="3">"#,
            r#"<iterative id="w" until="true">"#,
        );
        let e = export(&parse_plan(&src).unwrap(), &v).unwrap_err();
        assert!(e.to_string().contains("`w`"), "{e}");
    }

    #[test]
    fn import_refuses_impossible_jump_counts_without_panicking() {
        for repeat in ["1e30", "1.5", "4294967295"] {
            let doc = format!(
                r#"{{"fileType": "Plan", "mission": {{"items": [
                {{"type": "SimpleItem", "command": 16, "doJumpId": 1, "frame": 3, "params": [0, 0, 0, null, 41.0, 2.0, 10]}},
                {{"type": "SimpleItem", "command": 177, "doJumpId": 2, "frame": 3, "params": [1, {repeat}, 0, 0, 0, 0, 0]}}
            ]}}}}"#
            );
            let e = import(&doc, "x").unwrap_err();
            assert!(
                matches!(&e, QgcImportError::Item { index: 1, why } if why.contains("repeat count")),
                "{repeat}: {e}"
            );
        }
    }

    proptest::proptest! {
        /// A damaged `.plan` file is refused, never a panic.
        #[test]
        fn import_never_panics_on_mangled_files(cut in 0usize..6000, junk in "[\\[\\]{}:,\"0-9a-zA-Z .-]{0,8}") {
            let v = VehicleParams::rover();
            let doc = export(&parse_plan(PLAN).unwrap(), &v).unwrap().to_string();
            let mut s = doc.clone();
            let at = cut.min(s.len());
            s.insert_str(at, &junk);
            let _ = import(&s, "x");
            let _ = import(&doc[..at], "x");
        }
    }

    #[test]
    fn import_refuses_unknown_items() {
        let doc = json!({"fileType": "Plan", "mission": {"items": [
            {"type": "SimpleItem", "command": 16, "doJumpId": 1, "frame": 3, "params": [0, 0, 0, null, 41.0, 2.0, 10]},
            {"type": "SimpleItem", "command": 183, "doJumpId": 2, "frame": 3, "params": [0, 0, 0, 0, 0, 0, 0]}
        ]}});
        let e = import(&doc.to_string(), "x").unwrap_err();
        assert_eq!(
            e,
            QgcImportError::Item {
                index: 1,
                why: "MAV_CMD 183 is not supported".into()
            }
        );
        assert!(matches!(import("{", "x"), Err(QgcImportError::NotAPlan(_))));
    }
}
