//! The fleet service's wire types (`<namespace>/fleet/...`), shared with the launcher and the
//! stations ([`items`] pairs each item's name with its type). Plain structs and externally
//! tagged enums only: the middleware encodes with postcard, which is not self-describing.

pub mod items;

use serde::{Deserialize, Serialize};

/// One vehicle as the fleet layer sees it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct VehicleStatus {
    /// Its name in the fleet plan (`surveyor`).
    pub id: String,
    /// Its services' prefix (`rover1`).
    pub prefix: String,
    /// Separation priority (higher wins).
    pub priority: i32,
    /// The VAS's flight state, as text (`WAYPOINT_NAVIGATION`), once known.
    pub state: Option<String>,
    /// Last position: (lat, lon), degrees.
    pub position: Option<(f64, f64)>,
    /// The flight plan it was last given (its name).
    pub plan: Option<String>,
    /// That plan's progress, 0..1.
    pub progress: f64,
    /// Its last plan completed (or its investigation ended).
    pub done: bool,
    /// Held for separation.
    pub holding: bool,
    /// Paused by a command or the fleet plan.
    pub paused: bool,
    /// The nominal waypoints of the plan it was last given, (lat, lon), at most
    /// [`ROUTE_POINTS`], for a station's map.
    pub route: Vec<(f64, f64)>,
    /// An aircraft's flight so far against its plans: the take-off, the altitudes flown, the
    /// landing (`None` for a rover).
    pub aircraft: Option<crate::aircraft::AircraftSummary>,
}

/// Most points of a [`VehicleStatus::route`] (a longer plan is thinned evenly, ends kept).
pub const ROUTE_POINTS: usize = 300;

/// `points` thinned to at most `max` (>= 2), first and last kept.
pub fn thin(points: &[(f64, f64)], max: usize) -> Vec<(f64, f64)> {
    let max = max.max(2);
    if points.len() <= max {
        return points.to_vec();
    }
    let last = points.len() - 1;
    (0..max).map(|k| points[k * last / (max - 1)]).collect()
}

/// A point of interest a vehicle's detector reported.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Detection {
    /// The detector's number for it.
    pub id: u32,
    /// The vehicle that reported it.
    pub by: String,
    /// Latitude, degrees.
    pub lat: f64,
    /// Longitude, degrees.
    pub lon: f64,
    /// How sure the detector was, 0..1.
    #[serde(default)]
    pub confidence: f32,
    /// Seconds into the fleet plan when it was reported.
    pub at_s: f64,
    /// Visited by an investigator (which, and when).
    pub visited: Option<(String, f64)>,
    /// The operator deleted it: no investigator goes there.
    #[serde(default)]
    pub deleted: bool,
}

/// Who reported the points the operator adds ([`PointEdit::Add`]).
pub const OPERATOR: &str = "operator";

/// An operator's change to the points the investigators visit (the fleet's `edit_points`),
/// made mid-flight from a station's fleet view. A point is named by who reported it and its
/// number (`("surveyor", 3)`; `("operator", 1)` for the operator's own).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum PointEdit {
    /// A point of the operator's own, to visit as a detection (`by` [`OPERATOR`], numbered
    /// from 1).
    Add {
        /// Latitude, degrees.
        lat: f64,
        /// Longitude, degrees.
        lon: f64,
    },
    /// No investigator goes to this point (it stays listed, marked deleted; a visit already
    /// under way is finished).
    Delete {
        /// Who reported it.
        by: String,
        /// Its number.
        id: u32,
    },
    /// Visit these pending points first, in this order; the others after them, nearest first.
    Order {
        /// The points, first to visit first.
        points: Vec<(String, u32)>,
    },
}

/// Separation figures.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct SeparationStatus {
    /// The rule's minimum distance (0: no rule).
    pub min_m: f64,
    /// Times a vehicle was held on a conflict.
    pub holds: u32,
    /// Times two vehicles came closer than the minimum.
    pub violations: u32,
    /// The closest two vehicles came, metres (`None` before two positions are known).
    pub closest_m: Option<f64>,
    /// Times a vehicle entered a static obstacle (below its top).
    #[serde(default)]
    pub obstacle_entries: u32,
    /// Visits routed round an obstacle (the straight line was not clear).
    #[serde(default)]
    pub detours: u32,
}

/// Variable `<namespace>/fleet/status`: the whole fleet, published on every change (at most
/// 4 times a second) and every 2 s.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct FleetStatus {
    /// The fleet plan's name.
    pub plan: String,
    /// Seconds since the fleet plan started.
    pub elapsed_s: f64,
    /// The fleet plan has ended successfully.
    pub done: bool,
    /// Why it failed, if it did.
    pub failed: Option<String>,
    /// The statement being run (innermost), as `line:col <element>`.
    pub doing: Vec<String>,
    /// The vehicles, in plan order.
    pub vehicles: Vec<VehicleStatus>,
    /// The detections, in report order.
    pub detections: Vec<Detection>,
    /// Ids of the detections in the order they were visited.
    pub visit_order: Vec<u32>,
    /// Separation.
    pub separation: SeparationStatus,
    /// The fleet plan's variables and their values now, in declaration order.
    pub vars: Vec<(String, crate::api::VarValue)>,
    /// The static obstacles of the fleet plan, for the maps.
    #[serde(default)]
    pub obstacles: Vec<ObstacleView>,
    /// The pending points the operator put first, in their order ([`PointEdit::Order`]).
    #[serde(default)]
    pub visit_first: Vec<(String, u32)>,
}

/// A static obstacle as the maps draw it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ObstacleView {
    /// Its name.
    pub name: String,
    /// Its height above home, metres.
    pub height_m: f64,
    /// Its outline, `(lat, lon)` degrees.
    pub polygon: Vec<(f64, f64)>,
}

impl FleetStatus {
    /// Visited detections over those to visit, the deleted ones aside (1 when none is
    /// left to visit).
    pub fn visited_ratio(&self) -> f64 {
        let to_visit = self.detections.iter().filter(|d| !d.deleted).count();
        if to_visit == 0 {
            1.0
        } else {
            let v = self
                .detections
                .iter()
                .filter(|d| d.visited.is_some() && !d.deleted)
                .count();
            v as f64 / to_visit as f64
        }
    }

    /// The human-readable summary the launcher prints at the end.
    pub fn text(&self, mission: &str) -> String {
        let visited = self
            .detections
            .iter()
            .filter(|d| d.visited.is_some())
            .count();
        let mut s = format!(
            "mission {mission}: fleet plan `{}` {} in {:.1} s\n",
            self.plan,
            if self.done {
                "completed"
            } else {
                "NOT completed"
            },
            self.elapsed_s
        );
        let order: Vec<String> = self.visit_order.iter().map(|i| format!("#{i}")).collect();
        let deleted = self.detections.iter().filter(|d| d.deleted).count();
        let added = self.detections.iter().filter(|d| d.by == OPERATOR).count();
        let by_operator = match (added, deleted) {
            (0, 0) => String::new(),
            (a, d) => format!(" ({a} added, {d} deleted by the operator)"),
        };
        s += &format!(
            "  detections: {} reported, {visited} visited (ratio {:.2}){by_operator}, in the order {}\n",
            self.detections.len(),
            self.visited_ratio(),
            if order.is_empty() {
                "-".into()
            } else {
                order.join(" ")
            }
        );
        let sep = &self.separation;
        s += &format!(
            "  separation: minimum {:.1} m, {} holds, {} violations, closest {}\n",
            sep.min_m,
            sep.holds,
            sep.violations,
            sep.closest_m.map_or("-".into(), |d| format!("{d:.1} m"))
        );
        if !self.obstacles.is_empty() {
            let names: Vec<&str> = self.obstacles.iter().map(|o| o.name.as_str()).collect();
            s += &format!(
                "  obstacles: {} ({}), {} visits routed round them, entered {} times\n",
                names.len(),
                names.join(", "),
                sep.detours,
                sep.obstacle_entries
            );
        }
        for v in &self.vehicles {
            s += &format!(
                "  {} ({}): {} {}\n",
                v.id,
                v.prefix,
                v.plan.as_deref().unwrap_or("no plan"),
                if v.done { "done" } else { "not done" }
            );
            if let Some(a) = &v.aircraft {
                // The flight's own lines, under the vehicle's.
                for line in a.text().lines() {
                    s += &format!("  {line}\n");
                }
            }
        }
        if let Some(f) = &self.failed {
            s += &format!("  failed: {f}\n");
        }
        s
    }
}
