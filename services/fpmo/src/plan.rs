//! The station's own copy of a flight plan: parsed and expanded here with the FPMa's library, so
//! the page can list the legs and draw the generated waypoints without asking the vehicle for
//! them (the FPMa publishes progress, not geometry, and the radio has no bandwidth to spare).
//! A leg change confirmed by the FPMa is applied to this copy the same way
//! ([`fpma::parse::modify_node`]), so the map is redrawn with the new waypoints.

use fpma::exec::expand_nominal;
use fpma::model::{FlightPlan, Node, NodeKind, Stage};
use fpma::parse::{modify_node, parse_plan};
use fpma::vehicle::VehicleParams;
use serde::Serialize;

/// One row of the legs table.
#[derive(Clone, Debug, Serialize)]
pub struct LegInfo {
    /// Leg id (what `goto_leg` and `modify_leg` take).
    pub id: String,
    /// Stage name.
    pub stage: &'static str,
    /// Nesting depth inside loops and alternatives.
    pub depth: usize,
    /// `TF`, `hold`, `scan`, `iterative`...
    pub kind: String,
    /// The leg's parameters as the model has them (metres, degrees, m/s), for display and editing.
    pub params: serde_json::Value,
    /// Nominal length of the leg's waypoints, metres (0 for constructs).
    pub length_m: f64,
}

/// One generated waypoint, for the map.
#[derive(Clone, Debug, Serialize)]
pub struct MapPoint {
    /// Latitude, degrees.
    pub lat: f64,
    /// Longitude, degrees.
    pub lon: f64,
    /// Leg id.
    pub leg: String,
    /// Part of a hold or loop shown once.
    pub waits: bool,
}

/// A plan as the station holds it.
#[derive(Clone, Debug)]
pub struct LocalPlan {
    /// File name it was loaded from.
    pub file: String,
    /// The XML as uploaded.
    pub xml: String,
    /// Parsed.
    pub plan: FlightPlan,
    /// Legs in document order.
    pub legs: Vec<LegInfo>,
    /// Nominal waypoints.
    pub waypoints: Vec<MapPoint>,
}

fn kind_name(k: &NodeKind) -> String {
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

/// Distance between two points, metres (haversine: display only).
pub fn distance_m(a: (f64, f64), b: (f64, f64)) -> f64 {
    let r = 6_371_008.8;
    let (la1, la2) = (a.0.to_radians(), b.0.to_radians());
    let dla = la2 - la1;
    let dlo = (b.1 - a.1).to_radians();
    let h = (dla / 2.0).sin().powi(2) + la1.cos() * la2.cos() * (dlo / 2.0).sin().powi(2);
    2.0 * r * h.sqrt().min(1.0).asin()
}

impl LocalPlan {
    /// Parses and expands `xml` for `vehicle`.
    ///
    /// # Errors
    /// `file:line:col: what` for a plan the FPMa would refuse too; a plan that never ends.
    pub fn load(file: &str, xml: &str, vehicle: &VehicleParams) -> Result<Self, String> {
        let plan = parse_plan(xml, vehicle).map_err(|e| format!("{file}:{e}"))?;
        Self::build(file, xml, plan, vehicle)
    }

    fn build(
        file: &str,
        xml: &str,
        plan: FlightPlan,
        vehicle: &VehicleParams,
    ) -> Result<Self, String> {
        let wps = expand_nominal(plan.clone(), vehicle.clone()).map_err(|e| e.to_string())?;
        let waypoints: Vec<MapPoint> = wps
            .iter()
            .map(|w| MapPoint {
                lat: w.lat,
                lon: w.lon,
                leg: w.leg.clone(),
                waits: w.waits,
            })
            .collect();
        let mut legs = Vec::new();
        fn walk(nodes: &[Node], stage: Stage, depth: usize, out: &mut Vec<LegInfo>) {
            for n in nodes {
                let params = if n.kind.is_leaf() {
                    serde_json::to_value(&n.kind).unwrap_or_default()
                } else {
                    serde_json::Value::Null
                };
                out.push(LegInfo {
                    id: n.id.clone(),
                    stage: stage.name(),
                    depth,
                    kind: kind_name(&n.kind),
                    params,
                    length_m: 0.0,
                });
                for b in n.kind.bodies() {
                    walk(b, stage, depth + 1, out);
                }
            }
        }
        for s in Stage::ALL {
            walk(plan.stage(s), s, 0, &mut legs);
        }
        for l in &mut legs {
            let pts: Vec<(f64, f64)> = waypoints
                .iter()
                .filter(|w| w.leg == l.id)
                .map(|w| (w.lat, w.lon))
                .collect();
            l.length_m = pts.windows(2).map(|p| distance_m(p[0], p[1])).sum();
        }
        Ok(Self {
            file: file.to_owned(),
            xml: xml.to_owned(),
            plan,
            legs,
            waypoints,
        })
    }

    /// This plan with leg `id` changed as the FPMa changed it.
    ///
    /// # Errors
    /// Unknown leg, or a change the parser refuses.
    pub fn modified(
        &self,
        id: &str,
        changes: &[(String, String)],
        vehicle: &VehicleParams,
    ) -> Result<Self, String> {
        let node = self
            .plan
            .find(id)
            .ok_or_else(|| format!("unknown leg `{id}`"))?;
        let new = modify_node(node, changes, &self.plan, vehicle).map_err(|e| e.to_string())?;
        let mut plan = self.plan.clone();
        fn replace(nodes: &mut [Node], new: &Node) -> bool {
            for n in nodes.iter_mut() {
                if n.id == new.id {
                    *n = new.clone();
                    return true;
                }
                let found = match &mut n.kind {
                    NodeKind::Iterative(it) => replace(&mut it.body, new),
                    NodeKind::Alternative(a) => {
                        a.branches.iter_mut().any(|b| replace(&mut b.body, new))
                    }
                    _ => false,
                };
                if found {
                    return true;
                }
            }
            false
        }
        let mut done = false;
        for s in Stage::ALL {
            if replace(plan.stage_mut(s), &new) {
                done = true;
                break;
            }
        }
        if !done {
            return Err(format!("leg `{id}` not found"));
        }
        Self::build(&self.file, &self.xml, plan, vehicle)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn carpark() -> String {
        let p = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../config/flightplans/rover-carpark.xml"
        );
        std::fs::read_to_string(p).expect("rover-carpark.xml")
    }

    #[test]
    fn legs_and_waypoints_of_the_carpark_plan() {
        let v = VehicleParams::rover();
        let p = LocalPlan::load("carpark.xml", &carpark(), &v).unwrap();
        assert!(p.legs.iter().any(|l| l.kind == "scan"), "{:?}", p.legs);
        assert!(p.waypoints.len() > 10);
        let scan = p.legs.iter().find(|l| l.kind == "scan").unwrap();
        assert!(scan.params["spacing"].as_f64().unwrap() > 0.0);
        assert!(scan.length_m > 10.0);
    }

    #[test]
    fn wider_spacing_fewer_scan_waypoints() {
        let v = VehicleParams::rover();
        let p = LocalPlan::load("carpark.xml", &carpark(), &v).unwrap();
        let scan = p.legs.iter().find(|l| l.kind == "scan").unwrap().clone();
        let count = |p: &LocalPlan| p.waypoints.iter().filter(|w| w.leg == scan.id).count();
        let spacing = scan.params["spacing"].as_f64().unwrap();
        let q = p
            .modified(
                &scan.id,
                &[("spacing".into(), (spacing * 2.0).to_string())],
                &v,
            )
            .unwrap();
        assert!(count(&q) < count(&p), "{} !< {}", count(&q), count(&p));
        assert!(p.modified("nope", &[], &v).is_err());
    }

    #[test]
    fn broken_plan_names_its_line() {
        let e = LocalPlan::load(
            "x.xml",
            "<flightPlan name='x'><bogus/></flightPlan>",
            &VehicleParams::rover(),
        )
        .unwrap_err();
        assert!(e.starts_with("x.xml:1:"), "{e}");
    }
}
