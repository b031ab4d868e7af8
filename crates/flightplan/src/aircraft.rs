//! Flying a plan with an aircraft, as its pilot would: start by taking off, navigate once the
//! climb is done, and read the flight back as altitudes flown against the plan's and a
//! touchdown against the planned landing point. Pure; the launcher's station and the fleet
//! layer carry it out.

use crate::expand::{Waypoint, WaypointTag};
use crate::geo::{distance, GeoPoint};
use usal_types::{AllowedChanges, AltRef, FlightState, Position};

/// A climb counts as done this close to the take-off altitude, metres (or at 95 % of it).
const CLIMBED_WITHIN_M: f64 = 1.0;

/// The aircraft side of a plan: its altitudes, take-off and landing.
#[derive(Clone, Debug, PartialEq)]
pub struct AircraftPlan {
    /// What the plan's altitudes are measured from.
    pub alt_ref: AltRef,
    /// The altitude the take-off climbs to, in `alt_ref`.
    pub takeoff_alt: Option<f64>,
    /// The nominal waypoints, in stream order.
    pub points: Vec<PlannedPoint>,
    /// Where the plan lands, `(lat, lon)`.
    pub landing: Option<(f64, f64)>,
}

impl AircraftPlan {
    /// From a plan's nominal waypoint stream.
    pub fn of(alt_ref: AltRef, wps: &[Waypoint]) -> Self {
        Self {
            alt_ref,
            takeoff_alt: wps
                .iter()
                .find(|w| w.tag == WaypointTag::Takeoff)
                .map(|w| w.alt),
            points: wps
                .iter()
                .map(|w| PlannedPoint {
                    leg: w.leg.clone(),
                    alt: (w.tag == WaypointTag::Nav).then_some(w.alt),
                })
                .collect(),
            landing: wps
                .iter()
                .rev()
                .find(|w| w.tag == WaypointTag::Land)
                .map(|w| (w.lat, w.lon)),
        }
    }

    /// One flight of several plans: `next` flown after this one. The take-off stays this
    /// one's (the next's where this has none), the landing is the next's (where the flight now
    /// ends), the waypoints follow one another; returns the index of `next`'s first waypoint
    /// (for [`FlightRecord::next_plan`]).
    pub fn then(&mut self, next: Self) -> usize {
        let offset = self.points.len();
        if self.takeoff_alt.is_none() && offset == 0 {
            self.takeoff_alt = next.takeoff_alt;
        }
        self.points.extend(next.points);
        self.landing = next.landing;
        offset
    }

    /// The vehicle's altitude in the plan's reference.
    pub fn altitude(&self, p: &Position) -> f64 {
        match self.alt_ref {
            AltRef::Msl => p.alt,
            AltRef::Relative | AltRef::Terrain => p.alt_rel,
        }
    }

    /// Whether a climb to the take-off altitude is done (a plan without a take-off has none
    /// to wait for).
    pub fn climbed(&self, p: &Position) -> bool {
        self.takeoff_alt.is_none_or(|target| {
            let alt = self.altitude(p);
            alt >= target - CLIMBED_WITHIN_M || alt >= 0.95 * target
        })
    }
}

/// What the operator asks the VAS for next to fly a loaded plan, in `state`: a vehicle that
/// must take off before navigating (the VAS's allowed changes say so) takes off, and
/// navigates once `climbed`. `None`: nothing is due (or the allowed changes are not known).
pub fn start_request(
    state: FlightState,
    allowed: Option<&AllowedChanges>,
    climbed: bool,
) -> Option<FlightState> {
    use FlightState::{Parking, TakeOff, WaypointNavigation};
    match state {
        Parking => {
            let states = &allowed.filter(|a| a.from == Some(Parking))?.states;
            if states.contains(&WaypointNavigation) {
                Some(WaypointNavigation)
            } else if states.contains(&TakeOff) {
                Some(TakeOff)
            } else {
                None
            }
        }
        TakeOff if climbed => Some(WaypointNavigation),
        _ => None,
    }
}

/// A nominal waypoint of an aircraft's plan.
#[derive(Clone, Debug, PartialEq)]
pub struct PlannedPoint {
    /// The leg it belongs to (what the FPMa's reach events name).
    pub leg: String,
    /// The altitude it holds en route, in the plan's reference; `None` for a take-off's and
    /// a landing's (where the climb ends and the ground, not heights to hold).
    pub alt: Option<f64>,
}

/// The flight of an aircraft, recorded as it goes.
#[derive(Clone, Debug, Default)]
pub struct FlightRecord {
    /// The highest altitude flown, in the plan's reference.
    highest: Option<f64>,
    /// At each waypoint the FPMa reported reached: (its nominal index, the altitude flown).
    at_waypoints: Vec<(usize, f64)>,
    /// It left the ground.
    took_off: bool,
    /// Where it came to rest after flying, `(lat, lon)`, once parked (landed and disarmed).
    parked_at: Option<(f64, f64)>,
    /// The plan's waypoint the next reach is looked for from.
    next_index: usize,
}

impl FlightRecord {
    /// A position report.
    pub fn position(&mut self, plan: &AircraftPlan, p: &Position) {
        let alt = plan.altitude(p);
        self.highest = Some(self.highest.map_or(alt, |h| h.max(alt)));
        if p.alt_rel > 2.0 {
            self.took_off = true;
        }
    }

    /// The flight goes on with the plan whose first waypoint is `index` ([`AircraftPlan::then`]).
    pub fn next_plan(&mut self, index: usize) {
        self.next_index = index;
    }

    /// The FPMa reported a waypoint of `leg` reached, the vehicle last seen at `p`: the plan's
    /// next waypoint of that leg. Waypoints before it were not flown (a leg's first point
    /// where the vehicle already was: a plan starting from where it is); a reach of no leg
    /// ahead (an operator's change) is not compared.
    pub fn reached(&mut self, plan: &AircraftPlan, leg: &str, p: Option<&Position>) {
        let Some(k) = plan
            .points
            .iter()
            .skip(self.next_index)
            .position(|w| w.leg == leg)
            .map(|k| k + self.next_index)
        else {
            return;
        };
        self.next_index = k + 1;
        if let Some(p) = p {
            self.at_waypoints.push((k, plan.altitude(p)));
        }
    }

    /// The VAS's state changed, the vehicle last seen at `p`.
    pub fn state(&mut self, state: FlightState, p: Option<&Position>) {
        if state == FlightState::Parking && self.took_off {
            self.parked_at = p.map(|p| (p.lat, p.lon));
        } else if state != FlightState::Parking {
            self.parked_at = None;
        }
    }

    /// Whether it has landed and parked after flying.
    pub fn parked_after_flight(&self) -> bool {
        self.parked_at.is_some()
    }

    /// The flight summed up against `plan`.
    pub fn summary(&self, plan: &AircraftPlan) -> AircraftSummary {
        let en_route: Vec<(f64, f64)> = self
            .at_waypoints
            .iter()
            .filter_map(|(i, flown)| Some((plan.points.get(*i)?.alt?, *flown)))
            .collect();
        let worst = en_route
            .iter()
            .map(|(planned, flown)| flown - planned)
            .fold(None::<f64>, |w, d| {
                Some(w.map_or(d, |w| if d.abs() > w.abs() { d } else { w }))
            });
        AircraftSummary {
            alt_ref: plan.alt_ref.to_string(),
            took_off: self.took_off,
            highest_m: self.highest,
            takeoff_alt_m: plan.takeoff_alt,
            waypoints_checked: en_route.len(),
            planned_alt_m: range(en_route.iter().map(|w| w.0)),
            flown_alt_m: range(en_route.iter().map(|w| w.1)),
            worst_alt_error_m: worst,
            landed: self.parked_at.is_some(),
            landing_error_m: match (self.parked_at, plan.landing) {
                (Some(a), Some(b)) => {
                    Some(distance(GeoPoint::new(a.0, a.1), GeoPoint::new(b.0, b.1)))
                }
                _ => None,
            },
            plans_landing: plan.landing.is_some(),
        }
    }
}

fn range(values: impl Iterator<Item = f64>) -> Option<(f64, f64)> {
    values.fold(None, |r, v| {
        Some(r.map_or((v, v), |(lo, hi): (f64, f64)| (lo.min(v), hi.max(v))))
    })
}

/// An aircraft's flight in a run's summary.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct AircraftSummary {
    /// The reference of every altitude below (`MSL`, `REL`, `AGL`).
    pub alt_ref: String,
    /// It left the ground.
    pub took_off: bool,
    /// The highest altitude flown.
    pub highest_m: Option<f64>,
    /// The plan's take-off altitude.
    pub takeoff_alt_m: Option<f64>,
    /// En-route waypoints whose altitude was compared.
    pub waypoints_checked: usize,
    /// Their planned altitudes, lowest and highest.
    pub planned_alt_m: Option<(f64, f64)>,
    /// The altitudes flown there, lowest and highest.
    pub flown_alt_m: Option<(f64, f64)>,
    /// The largest difference flown minus planned (signed: below the plan is negative).
    pub worst_alt_error_m: Option<f64>,
    /// The plan ends with a landing.
    pub plans_landing: bool,
    /// It landed and is parked, disarmed.
    pub landed: bool,
    /// How far from the planned landing point it came to rest, metres.
    pub landing_error_m: Option<f64>,
}

impl AircraftSummary {
    /// The lines of the run's summary.
    pub fn text(&self) -> String {
        let r = &self.alt_ref;
        let mut s = match (self.took_off, self.takeoff_alt_m, self.highest_m) {
            (false, _, _) => "  take-off: the aircraft never left the ground\n".to_owned(),
            (true, Some(t), Some(h)) => {
                format!("  take-off: to {t:.0} m {r} planned; highest flown {h:.1} m\n")
            }
            (true, _, h) => format!("  flown: highest {:.1} m {r}\n", h.unwrap_or(f64::NAN)),
        };
        if let (Some(p), Some(f), Some(w)) =
            (self.planned_alt_m, self.flown_alt_m, self.worst_alt_error_m)
        {
            s += &format!(
                "  altitude: {} waypoints planned at {} m {r}, flown at {} m (largest difference {w:+.1} m)\n",
                self.waypoints_checked,
                span(p),
                span(f),
            );
        }
        if self.plans_landing {
            s += &match (self.landed, self.landing_error_m) {
                (true, Some(d)) => {
                    format!("  landing: on the ground, disarmed, {d:.1} m from the planned point\n")
                }
                _ => "  landing: NOT on the ground and parked at the end\n".to_owned(),
            };
        }
        s
    }
}

fn span((lo, hi): (f64, f64)) -> String {
    if (hi - lo).abs() < 0.05 {
        format!("{lo:.1}")
    } else {
        format!("{lo:.1}-{hi:.1}")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use usal_types::VehicleKind;

    fn wp(alt: f64, tag: WaypointTag, lat: f64, leg: &str) -> Waypoint {
        Waypoint {
            lat,
            lon: 2.0,
            alt,
            speed: 5.0,
            fly_over: false,
            leg: leg.into(),
            tag,
            waits: false,
            land_start: false,
            fix_crossing: false,
            seq: 0,
            version: 0,
        }
    }

    fn at(alt_rel: f64, lat: f64) -> Position {
        Position {
            lat,
            lon: 2.0,
            alt: alt_rel + 100.0,
            heading: 0.0,
            speed: 0.0,
            alt_rel,
        }
    }

    fn plan() -> AircraftPlan {
        AircraftPlan::of(
            AltRef::Relative,
            &[
                wp(30.0, WaypointTag::Takeoff, 41.0, "takeoff"),
                wp(30.0, WaypointTag::Nav, 41.001, "mission.1"),
                wp(40.0, WaypointTag::Nav, 41.002, "mission.2"),
                wp(0.0, WaypointTag::Land, 41.0, "landing"),
            ],
        )
    }

    #[test]
    fn an_aircraft_takes_off_before_navigating_and_navigates_once_climbed() {
        let allowed = |states: Vec<FlightState>| AllowedChanges {
            from: Some(FlightState::Parking),
            kind: VehicleKind::Copter,
            states,
            commands: vec![],
            armed: false,
        };
        let copter = allowed(vec![FlightState::TakeOff, FlightState::Manual]);
        let rover = allowed(vec![FlightState::WaypointNavigation, FlightState::Manual]);
        use FlightState::*;
        assert_eq!(start_request(Parking, Some(&copter), false), Some(TakeOff));
        assert_eq!(
            start_request(Parking, Some(&rover), false),
            Some(WaypointNavigation)
        );
        // Not yet known what the VAS allows: nothing is asked.
        assert_eq!(start_request(Parking, None, true), None);
        assert_eq!(start_request(TakeOff, Some(&copter), false), None);
        assert_eq!(
            start_request(TakeOff, Some(&copter), true),
            Some(WaypointNavigation)
        );
        assert_eq!(start_request(WaypointNavigation, Some(&copter), true), None);
        let p = plan();
        assert!(!p.climbed(&at(20.0, 41.0)));
        assert!(p.climbed(&at(29.2, 41.0)));
    }

    #[test]
    fn the_summary_compares_altitudes_en_route_and_the_touchdown_with_the_plan() {
        let p = plan();
        let mut f = FlightRecord::default();
        f.position(&p, &at(0.0, 41.0));
        f.state(FlightState::Parking, Some(&at(0.0, 41.0)));
        assert!(
            !f.parked_after_flight(),
            "parked before flying is not a landing"
        );
        f.position(&p, &at(30.5, 41.0));
        f.reached(&p, "takeoff", Some(&at(30.5, 41.0)));
        f.reached(&p, "mission.1", Some(&at(29.0, 41.001)));
        f.position(&p, &at(41.0, 41.002));
        f.reached(&p, "mission.2", Some(&at(39.5, 41.002)));
        f.reached(&p, "landing", Some(&at(0.0, 41.0001)));
        f.state(FlightState::Parking, Some(&at(0.0, 41.0001)));
        assert!(f.parked_after_flight());
        let s = f.summary(&p);
        assert!(s.took_off && s.landed);
        assert_eq!(s.waypoints_checked, 2);
        assert_eq!(s.planned_alt_m, Some((30.0, 40.0)));
        assert_eq!(s.flown_alt_m, Some((29.0, 39.5)));
        assert_eq!(s.worst_alt_error_m, Some(-1.0));
        assert_eq!(s.highest_m, Some(41.0));
        let d = s.landing_error_m.expect("landed");
        assert!((d - 11.1).abs() < 0.5, "{d}");
        let text = s.text();
        assert!(text.contains("largest difference -1.0 m"), "{text}");
        assert!(
            text.contains("disarmed, 11.1 m from the planned point"),
            "{text}"
        );
        // Still flying at the end: said so.
        let mut g = FlightRecord::default();
        g.position(&p, &at(30.0, 41.0));
        assert!(g.summary(&p).text().contains("NOT on the ground"));
    }

    #[test]
    fn a_flight_of_several_plans_checks_the_altitudes_of_each_en_route_only() {
        let nav = |alt, lat, leg| wp(alt, WaypointTag::Nav, lat, leg);
        let start = [
            wp(10.0, WaypointTag::Takeoff, 41.0, "takeoff"),
            nav(10.0, 41.001, "mission.1"),
        ];
        let mut flight = AircraftPlan::of(AltRef::Relative, &start);
        // Plans that start from where the vehicle is: their first point is not flown.
        let visit = [
            nav(10.0, 41.001, "mission.1"),
            nav(10.0, 41.002, "mission.2"),
        ];
        let home = [
            nav(10.0, 41.002, "mission.1"),
            wp(0.0, WaypointTag::Land, 41.0, "landing"),
        ];
        let mut f = FlightRecord::default();
        f.reached(&flight, "takeoff", Some(&at(9.6, 41.0)));
        f.reached(&flight, "mission.1", Some(&at(10.2, 41.001)));
        f.next_plan(flight.then(AircraftPlan::of(AltRef::Relative, &visit)));
        f.reached(&flight, "mission.2", Some(&at(9.9, 41.002)));
        f.next_plan(flight.then(AircraftPlan::of(AltRef::Relative, &home)));
        // Touchdown: the landing's reach, not the unflown point above it.
        f.reached(&flight, "landing", Some(&at(0.1, 41.0)));
        // A reach of no leg ahead (an operator's change) is not compared.
        f.reached(&flight, "hold-here.9", Some(&at(0.1, 41.0)));
        assert_eq!(flight.takeoff_alt, Some(10.0));
        assert_eq!(flight.landing, Some((41.0, 2.0)));
        let s = f.summary(&flight);
        assert_eq!(s.waypoints_checked, 2);
        assert_eq!(s.flown_alt_m, Some((9.9, 10.2)));
        assert!(s.worst_alt_error_m.is_some_and(|e| (e - 0.2).abs() < 1e-9));
    }
}
