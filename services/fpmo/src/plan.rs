//! Flight plans at the station: an upload is checked here with the FPMa's own parser before it
//! is sent (a broken file is refused with its line at once, without loading the radio), and the
//! plan drawn is the one the FPMa says it flies, its `plan` variable ([`PlanGeometry`]), so the
//! page shows plans another station uploaded, and a plan changed in flight is redrawn from the
//! vehicle's copy, not from a guess of the station's.

use flightplan::api::{MapPoint, PlanGeometry};
use flightplan::check;
use flightplan::geo::{self, GeoPoint};
use flightplan::model::{FlightPlan, Node, Stage};
use flightplan::vehicle::VehicleParams;
use serde::Serialize;

/// A plan file checked for upload.
#[derive(Clone, Debug)]
pub struct CheckedPlan {
    /// File name it is sent as.
    pub file: String,
    /// Parsed.
    pub plan: FlightPlan,
    /// Legs and constructs in it.
    pub legs: usize,
}

impl CheckedPlan {
    /// Parses and checks `xml` for `vehicle`, as the FPMa will ([`flightplan::check::load`]).
    ///
    /// # Errors
    /// `file:line:col: what` for a plan the FPMa would refuse too; a plan that never ends.
    pub fn check(file: &str, xml: &str, vehicle: &VehicleParams) -> Result<Self, String> {
        let plan = check::load(xml, vehicle)
            .map_err(|e| e.in_file(file))?
            .plan()
            .clone();
        fn count(nodes: &[Node]) -> usize {
            nodes
                .iter()
                .map(|n| 1 + n.kind.bodies().iter().map(|b| count(b)).sum::<usize>())
                .sum()
        }
        let legs = Stage::ALL.into_iter().map(|s| count(plan.stage(s))).sum();
        Ok(Self {
            file: file.to_owned(),
            plan,
            legs,
        })
    }
}

/// One row of the legs table.
#[derive(Clone, Debug, Serialize)]
pub struct LegInfo {
    /// Leg id (what `goto_leg` and `modify_leg` take).
    pub id: String,
    /// Stage name.
    pub stage: &'static str,
    /// Nesting depth inside loops and alternatives.
    pub depth: u8,
    /// `TF`, `hold HF`, `scan`, `iterative`...
    pub kind: String,
    /// Parameters `modify_leg` can change (XML attribute names; metres, degrees, m/s).
    pub params: serde_json::Map<String, serde_json::Value>,
    /// Length of the leg's drawn waypoints, metres (0 for constructs).
    pub length_m: f64,
}

/// The page's view of a plan (`GET /api/plan`).
#[derive(Clone, Debug, Serialize)]
pub struct PlanView {
    /// The station's revision of the drawing (grows with every geometry received).
    pub rev: u64,
    /// Plan version at the FPMa.
    pub version: u64,
    /// Where the FPMa got it from (the uploaded file name).
    pub file: String,
    /// Plan name.
    pub name: String,
    /// Legs in document order.
    pub legs: Vec<LegInfo>,
    /// Nominal waypoints, possibly thinned by the FPMa.
    pub waypoints: Vec<MapPoint>,
    /// Waypoints of the plan before thinning.
    pub total_points: u32,
    /// The FPMa left some legs out.
    pub legs_truncated: bool,
    /// Stages the plan has, in flying order (what `goto_stage` accepts).
    pub stages: Vec<&'static str>,
    /// Emergency rules by name (what `emergency` accepts).
    pub rules: Vec<String>,
}

/// Distance between two `(lat, lon)` points, metres: the FPMa's own geodesy, so the station
/// measures legs as the vehicle flies them.
pub fn distance_m(a: (f64, f64), b: (f64, f64)) -> f64 {
    geo::distance(GeoPoint::new(a.0, a.1), GeoPoint::new(b.0, b.1))
}

impl PlanView {
    /// What the page draws of `g`, as the station's revision `rev`.
    pub fn of(g: &PlanGeometry, rev: u64) -> Self {
        let waypoints = g.map_points();
        let stages = Stage::ALL
            .into_iter()
            .filter(|s| g.legs.iter().any(|l| l.stage == *s))
            .map(Stage::name)
            .collect();
        let legs = g
            .legs
            .iter()
            .map(|l| {
                let pts: Vec<(f64, f64)> = waypoints
                    .iter()
                    .filter(|w| w.leg == l.id)
                    .map(|w| (w.lat, w.lon))
                    .collect();
                LegInfo {
                    id: l.id.clone(),
                    stage: l.stage.name(),
                    depth: l.depth,
                    kind: l.kind.clone(),
                    params: l
                        .params
                        .iter()
                        .map(|(k, v)| (k.clone(), serde_json::json!(v)))
                        .collect(),
                    length_m: pts.windows(2).map(|p| distance_m(p[0], p[1])).sum(),
                }
            })
            .collect();
        Self {
            rev,
            version: g.version,
            file: g.source.clone(),
            name: g.name.clone(),
            legs,
            waypoints,
            total_points: g.total_points,
            legs_truncated: g.legs_truncated,
            stages,
            rules: g.rules.clone(),
        }
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
    fn view_of_the_fpma_geometry() {
        let v = VehicleParams::rover();
        let c = CheckedPlan::check("carpark.xml", &carpark(), &v).unwrap();
        let nominal = check::load(&carpark(), &v).unwrap();
        let g = PlanGeometry::of(&c.plan, nominal.nominal(), 2, "carpark.xml");
        assert_eq!(c.legs, g.legs.len());
        let view = PlanView::of(&g, 7);
        assert_eq!(
            (view.rev, view.version, view.file.as_str()),
            (7, 2, "carpark.xml")
        );
        assert!(view.waypoints.len() > 10);
        let scan = view.legs.iter().find(|l| l.kind == "scan").unwrap();
        assert_eq!(scan.params["spacing"], 6.0);
        assert!(scan.length_m > 10.0);
        assert!(view.waypoints.iter().any(|w| w.leg == scan.id));
        assert_eq!(view.stages, ["departure", "mission", "approach"]);
        assert_eq!(view.rules, ["low-battery"]);
        let j = serde_json::to_value(&view).unwrap();
        assert!(j["waypoints"][0]["lat"].as_f64().unwrap() > 41.0);
    }

    #[test]
    fn broken_plan_names_its_line() {
        let e = CheckedPlan::check(
            "x.xml",
            "<flightPlan name='x'><bogus/></flightPlan>",
            &VehicleParams::rover(),
        )
        .unwrap_err();
        assert!(e.starts_with("x.xml:1:"), "{e}");
    }
}
