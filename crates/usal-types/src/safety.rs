//! Flight-safety types shared by the services: the geofence a plan carries (checked by the FPMa
//! on plans and changes, by the VAS on waypoints, uploaded to the autopilot), the ground
//! station's heartbeat the VAS follows to detect a lost ground link, and the `failsafe` event
//! the VAS raises when one of them acts.
//!
//! The fence geometry is plain flat-earth arithmetic in a local east/north frame around the
//! fence's home: fences are a few kilometres across, where the error against the geodesic
//! (under 0.1 % at 10 km) is far below any margin an operator draws a fence with.

use serde::{Deserialize, Serialize};

/// Mean Earth radius, metres (the spherical model of the fence checks).
const EARTH_RADIUS_M: f64 = 6_371_008.8;

/// What the autopilot does when the vehicle leaves the fence (ArduPilot `FENCE_ACTION`).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum FenceAction {
    /// Report only (an alarm), keep going.
    Report,
    /// Return to the launch point.
    #[default]
    ReturnToLaunch,
    /// Stop and hold where it is.
    Hold,
}

impl FenceAction {
    /// The name in plans and logs: `report`, `rtl`, `hold`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Report => "report",
            Self::ReturnToLaunch => "rtl",
            Self::Hold => "hold",
        }
    }

    /// ArduPilot's `FENCE_ACTION` value for it (Rover: 0 report, 1 RTL, 2 hold).
    pub fn ardupilot_param(self) -> f32 {
        match self {
            Self::Report => 0.0,
            Self::ReturnToLaunch => 1.0,
            Self::Hold => 2.0,
        }
    }

    /// The action an ArduPilot `FENCE_ACTION` value stands for (unknown values: RTL).
    pub fn from_ardupilot_param(v: f32) -> Self {
        match v.round() as i64 {
            0 => Self::Report,
            2 => Self::Hold,
            _ => Self::ReturnToLaunch,
        }
    }
}

impl std::str::FromStr for FenceAction {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "report" => Ok(Self::Report),
            "rtl" => Ok(Self::ReturnToLaunch),
            "hold" => Ok(Self::Hold),
            _ => Err(format!("`{s}`: expected report, rtl or hold")),
        }
    }
}

/// A geofence: a circle (maximum distance from home), a ceiling (maximum height above home)
/// and/or an inclusion polygon. The vehicle must stay inside every part that is set.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Fence {
    /// The home the distance is measured from: (lat, lon), degrees.
    pub home: (f64, f64),
    /// Largest horizontal distance from `home`, metres.
    pub max_distance_m: Option<f64>,
    /// Largest height above home, metres.
    pub max_height_m: Option<f64>,
    /// Inclusion polygon (lat, lon), degrees; empty: none. Closed implicitly.
    pub polygon: Vec<(f64, f64)>,
    /// What the autopilot does on a breach.
    pub action: FenceAction,
}

impl Fence {
    /// Whether any limit is set.
    pub fn is_empty(&self) -> bool {
        self.max_distance_m.is_none() && self.max_height_m.is_none() && self.polygon.is_empty()
    }

    /// Checks that the fence itself is usable: finite coordinates, positive limits, a polygon
    /// of at least 3 vertices.
    ///
    /// # Errors
    /// What is wrong, e.g. `maxDistance -5 must be above 0`.
    pub fn validate(&self) -> Result<(), String> {
        let coord_ok = |(lat, lon): (f64, f64)| {
            lat.is_finite() && lon.is_finite() && lat.abs() <= 90.0 && lon.abs() <= 180.0
        };
        if !coord_ok(self.home) {
            return Err(format!(
                "home {},{} is not a latitude,longitude",
                self.home.0, self.home.1
            ));
        }
        for (name, v) in [
            ("maxDistance", self.max_distance_m),
            ("maxHeight", self.max_height_m),
        ] {
            if let Some(v) = v {
                if !(v.is_finite() && v > 0.0) {
                    return Err(format!("{name} {v} must be above 0"));
                }
            }
        }
        if !self.polygon.is_empty() && self.polygon.len() < 3 {
            return Err(format!(
                "the fence polygon has {} points: at least 3",
                self.polygon.len()
            ));
        }
        if self.polygon.len() > 1000 {
            return Err(format!(
                "the fence polygon has {} points: at most 1000",
                self.polygon.len()
            ));
        }
        if let Some(p) = self.polygon.iter().find(|p| !coord_ok(**p)) {
            return Err(format!(
                "fence point {},{} is not a latitude,longitude",
                p.0, p.1
            ));
        }
        Ok(())
    }

    /// East/north metres of `p` from home.
    fn local(&self, (lat, lon): (f64, f64)) -> (f64, f64) {
        let lat0 = self.home.0.to_radians();
        let mut dlon = lon - self.home.1;
        if dlon > 180.0 {
            dlon -= 360.0;
        } else if dlon < -180.0 {
            dlon += 360.0;
        }
        (
            dlon.to_radians() * lat0.cos() * EARTH_RADIUS_M,
            (lat - self.home.0).to_radians() * EARTH_RADIUS_M,
        )
    }

    /// The latitude, longitude `east`/`north` metres from home.
    fn geo(&self, (east, north): (f64, f64)) -> (f64, f64) {
        let lat0 = self.home.0.to_radians();
        (
            self.home.0 + (north / EARTH_RADIUS_M).to_degrees(),
            self.home.1 + (east / (EARTH_RADIUS_M * lat0.cos())).to_degrees(),
        )
    }

    /// The fence in force when a plan brings `plan` to a vehicle whose own fence is `self`:
    /// the plan's fence may only narrow the vehicle's. Each part of `plan` must lie inside
    /// `self` (polygon vertices and edges, the circle at [`Self::CIRCLE_SAMPLES`] points, the
    /// ceiling); the result keeps the plan's parts and the vehicle's parts the plan does not
    /// set, and the plan's action.
    ///
    /// # Errors
    /// The part of the plan's fence that reaches outside the vehicle's, and where.
    pub fn narrowed_by(&self, plan: &Fence) -> Result<Fence, String> {
        let outside = |part: &str, e: String| {
            format!("the plan's fence {part} reaches outside the vehicle's fence: {e}")
        };
        let n = plan.polygon.len();
        for (i, &p) in plan.polygon.iter().enumerate() {
            self.check_point(p, None)
                .map_err(|e| outside(&format!("vertex {}", i + 1), e))?;
        }
        for i in 0..n {
            self.check_segment(plan.polygon[i], plan.polygon[(i + 1) % n])
                .map_err(|e| outside(&format!("edge {}-{}", i + 1, (i + 1) % n + 1), e))?;
        }
        if let Some(r) = plan.max_distance_m {
            for k in 0..Self::CIRCLE_SAMPLES {
                let a = std::f64::consts::TAU * f64::from(k) / f64::from(Self::CIRCLE_SAMPLES);
                let p = plan.geo((r * a.sin(), r * a.cos()));
                self.check_point(p, None)
                    .map_err(|e| outside(&format!("circle ({r} m around its home)"), e))?;
            }
        }
        if let (Some(p), Some(v)) = (plan.max_height_m, self.max_height_m) {
            if p > v {
                return Err(format!(
                    "the plan's fence ceiling {p} m is above the vehicle's fence ceiling {v} m"
                ));
            }
        }
        let (home, max_distance_m) = match plan.max_distance_m {
            Some(r) => (plan.home, Some(r)),
            None => (self.home, self.max_distance_m),
        };
        let max_height_m = match (plan.max_height_m, self.max_height_m) {
            (Some(p), Some(v)) => Some(p.min(v)),
            (p, v) => p.or(v),
        };
        let polygon = if plan.polygon.is_empty() {
            self.polygon.clone()
        } else {
            plan.polygon.clone()
        };
        Ok(Fence {
            home,
            max_distance_m,
            max_height_m,
            polygon,
            action: plan.action,
        })
    }

    /// Points of a plan's circle checked against the vehicle's fence by
    /// [`Self::narrowed_by`] (a chord's sagitta is under 0.2 % of the radius).
    pub const CIRCLE_SAMPLES: u16 = 64;

    /// Horizontal distance of `p` from home, metres.
    pub fn distance_from_home_m(&self, p: (f64, f64)) -> f64 {
        let (e, n) = self.local(p);
        e.hypot(n)
    }

    /// Checks one point: `height` is its height above home when known.
    ///
    /// # Errors
    /// Which limit it breaks, e.g. `41.28,1.99 is 612 m from home (fence: 500 m)`.
    pub fn check_point(&self, p: (f64, f64), height: Option<f64>) -> Result<(), String> {
        if !(p.0.is_finite() && p.1.is_finite()) {
            return Err(format!("{},{} is not a position", p.0, p.1));
        }
        if let Some(max) = self.max_distance_m {
            let d = self.distance_from_home_m(p);
            if d > max {
                return Err(format!(
                    "{:.6},{:.6} is {d:.0} m from home (fence: {max} m)",
                    p.0, p.1
                ));
            }
        }
        if let (Some(max), Some(h)) = (self.max_height_m, height) {
            if !h.is_finite() || h > max {
                return Err(format!(
                    "{:.6},{:.6} is {h:.0} m above home (fence: {max} m)",
                    p.0, p.1
                ));
            }
        }
        if !self.polygon.is_empty() && !self.inside_polygon(p) {
            return Err(format!(
                "{:.6},{:.6} is outside the fence polygon",
                p.0, p.1
            ));
        }
        Ok(())
    }

    /// Checks the straight track from `a` to `b` (both already checked as points): it must
    /// not cross the polygon's edges nor leave the circle. Heights are checked at the ends.
    ///
    /// # Errors
    /// Where it leaves, e.g. `the track 41.27,1.98 -> 41.28,1.99 crosses the fence polygon`.
    pub fn check_segment(&self, a: (f64, f64), b: (f64, f64)) -> Result<(), String> {
        let (pa, pb) = (self.local(a), self.local(b));
        let track = || format!("the track {:.6},{:.6} -> {:.6},{:.6}", a.0, a.1, b.0, b.1);
        // The circle is convex: a track leaves it only if an end does, and the ends were
        // checked as points.
        if self.polygon.len() >= 3 {
            let poly: Vec<(f64, f64)> = self.polygon.iter().map(|p| self.local(*p)).collect();
            for i in 0..poly.len() {
                let (c, d) = (poly[i], poly[(i + 1) % poly.len()]);
                if segments_cross(pa, pb, c, d) {
                    return Err(format!("{} crosses the fence polygon", track()));
                }
            }
            // Both ends inside and no edge crossed, but a track through a vertex of a concave
            // polygon can still leave: check its midpoint too.
            let mid = ((a.0 + b.0) / 2.0, (a.1 + b.1) / 2.0);
            if !self.inside_polygon(mid) {
                return Err(format!("{} leaves the fence polygon", track()));
            }
        }
        Ok(())
    }

    /// Point in polygon (even-odd rule), in the local frame.
    pub fn inside_polygon(&self, p: (f64, f64)) -> bool {
        let (x, y) = self.local(p);
        let poly: Vec<(f64, f64)> = self.polygon.iter().map(|q| self.local(*q)).collect();
        let mut inside = false;
        let mut j = poly.len().wrapping_sub(1);
        for i in 0..poly.len() {
            let (xi, yi) = poly[i];
            let (xj, yj) = poly[j];
            if (yi > y) != (yj > y) && x < (xj - xi) * (y - yi) / (yj - yi) + xi {
                inside = !inside;
            }
            j = i;
        }
        inside
    }
}

/// Whether segments `a-b` and `c-d` properly cross (touching ends do not count).
fn segments_cross(a: (f64, f64), b: (f64, f64), c: (f64, f64), d: (f64, f64)) -> bool {
    let orient = |p: (f64, f64), q: (f64, f64), r: (f64, f64)| {
        (q.0 - p.0) * (r.1 - p.1) - (q.1 - p.1) * (r.0 - p.0)
    };
    let (d1, d2) = (orient(c, d, a), orient(c, d, b));
    let (d3, d4) = (orient(a, b, c), orient(a, b, d));
    d1 * d2 < 0.0 && d3 * d4 < 0.0
}

/// The ground station's liveness signal (variable `<station>/heartbeat`, about 2 Hz): the VAS
/// declares the ground link lost when it stops (see the VAS's `val::linkloss`).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StationHeartbeat {
    /// The station's name.
    pub station: String,
    /// Increases by one each beat.
    pub seq: u64,
}

/// Which failsafe acted.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum FailsafeKind {
    /// The ground link was lost.
    LinkLost,
    /// The ground link came back.
    LinkRestored,
    /// The vehicle left the fence (the autopilot's breach), or a waypoint outside it was
    /// refused.
    Fence,
    /// The battery ran low.
    Battery,
}

impl FailsafeKind {
    /// A short name for summaries: `link-lost`, `link-restored`, `fence`, `battery`.
    pub fn name(self) -> &'static str {
        match self {
            Self::LinkLost => "link-lost",
            Self::LinkRestored => "link-restored",
            Self::Fence => "fence",
            Self::Battery => "battery",
        }
    }
}

/// A failsafe acted (VAS event `failsafe`): what, what was done, in words.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Failsafe {
    /// Which one.
    pub kind: FailsafeKind,
    /// What the vehicle did: `hold`, `rtl`, `continue`, `resume`, `wait`, `refused`...
    pub action: String,
    /// For a human.
    pub text: String,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 200 m square around home with a notch cut into its east side.
    fn fence() -> Fence {
        let home: (f64, f64) = (41.275, 1.987);
        let m = 1.0 / 111_195.0;
        let k = m / home.0.to_radians().cos();
        let pt = |e: f64, n: f64| (home.0 + n * m, home.1 + e * k);
        Fence {
            home,
            max_distance_m: Some(150.0),
            max_height_m: Some(30.0),
            polygon: vec![
                pt(-100.0, -100.0),
                pt(100.0, -100.0),
                pt(100.0, -20.0),
                pt(20.0, 0.0),
                pt(100.0, 20.0),
                pt(100.0, 100.0),
                pt(-100.0, 100.0),
            ],
            action: FenceAction::Hold,
        }
    }

    fn at(e: f64, n: f64) -> (f64, f64) {
        let home: (f64, f64) = (41.275, 1.987);
        let m = 1.0 / 111_195.0;
        (home.0 + n * m, home.1 + e * m / home.0.to_radians().cos())
    }

    #[test]
    fn a_plan_fence_may_only_narrow_the_vehicle_fence() {
        let vehicle = fence();
        // Inside the notched square: the plan's polygon and ceiling, the vehicle's circle.
        let small = Fence {
            home: at(-40.0, 0.0),
            max_distance_m: None,
            max_height_m: Some(20.0),
            polygon: vec![
                at(-50.0, -50.0),
                at(0.0, -50.0),
                at(0.0, 50.0),
                at(-50.0, 50.0),
            ],
            action: FenceAction::Report,
        };
        let merged = vehicle.narrowed_by(&small).unwrap();
        assert_eq!(merged.polygon, small.polygon);
        assert_eq!(
            (merged.home, merged.max_distance_m),
            (vehicle.home, Some(150.0))
        );
        assert_eq!(
            (merged.max_height_m, merged.action),
            (Some(20.0), FenceAction::Report)
        );
        // A plan without a polygon keeps the vehicle's.
        let ceiling_only = Fence {
            polygon: vec![],
            ..small.clone()
        };
        assert_eq!(
            vehicle.narrowed_by(&ceiling_only).unwrap().polygon,
            vehicle.polygon
        );

        // Wider in each part: refused, naming the part.
        let e = vehicle
            .narrowed_by(&Fence {
                polygon: vec![at(-50.0, -50.0), at(60.0, 0.0), at(-50.0, 50.0)],
                ..small.clone()
            })
            .unwrap_err();
        assert!(
            e.contains("vertex 2") && e.contains("outside the fence polygon"),
            "{e}"
        );
        let e = vehicle
            .narrowed_by(&Fence {
                polygon: vec![at(50.0, -50.0), at(50.0, 50.0), at(-50.0, 0.0)],
                ..small.clone()
            })
            .unwrap_err();
        assert!(
            e.contains("edge 1-2") && e.contains("crosses the fence polygon"),
            "{e}"
        );
        let e = vehicle
            .narrowed_by(&Fence {
                polygon: vec![],
                max_distance_m: Some(80.0),
                ..small.clone()
            })
            .unwrap_err();
        assert!(e.contains("circle (80 m around its home)"), "{e}");
        let fits = Fence {
            polygon: vec![],
            home: at(-40.0, 0.0),
            max_distance_m: Some(50.0),
            ..small.clone()
        };
        let merged = vehicle.narrowed_by(&fits).unwrap();
        assert_eq!(
            (merged.home, merged.max_distance_m),
            (fits.home, Some(50.0))
        );
        let e = vehicle
            .narrowed_by(&Fence {
                max_height_m: Some(40.0),
                ..small
            })
            .unwrap_err();
        assert!(
            e.contains("ceiling 40 m is above the vehicle's fence ceiling 30 m"),
            "{e}"
        );
    }

    #[test]
    fn points_are_checked_against_circle_ceiling_and_polygon() {
        let f = fence();
        assert!(f.validate().is_ok());
        assert!(f.check_point(at(0.0, 0.0), Some(10.0)).is_ok());
        assert!(f.check_point(at(-90.0, 90.0), None).is_ok());
        let e = f.check_point(at(0.0, 140.0), None).unwrap_err();
        assert!(e.contains("outside the fence polygon"), "{e}");
        let far = Fence {
            polygon: vec![],
            ..fence()
        };
        let e = far.check_point(at(0.0, 160.0), None).unwrap_err();
        assert!(e.contains("160 m from home (fence: 150 m)"), "{e}");
        let e = f.check_point(at(0.0, 0.0), Some(31.0)).unwrap_err();
        assert!(e.contains("31 m above home"), "{e}");
        // In the notch.
        assert!(f.check_point(at(60.0, 0.0), None).is_err());
        assert!(f.check_point(at(f64::NAN, 0.0), None).is_err());
    }

    #[test]
    fn a_track_across_the_notch_is_refused_though_both_ends_are_inside() {
        let f = fence();
        let (a, b) = (at(60.0, -50.0), at(60.0, 50.0));
        assert!(f.check_point(a, None).is_ok() && f.check_point(b, None).is_ok());
        let e = f.check_segment(a, b).unwrap_err();
        assert!(e.contains("crosses the fence polygon"), "{e}");
        assert!(f.check_segment(at(-60.0, -50.0), at(-60.0, 50.0)).is_ok());
    }

    #[test]
    fn bad_fences_are_refused() {
        let mut f = fence();
        f.max_distance_m = Some(-1.0);
        assert!(f.validate().unwrap_err().contains("maxDistance -1"));
        let mut f = fence();
        f.polygon.truncate(2);
        assert!(f.validate().unwrap_err().contains("at least 3"));
        let mut f = fence();
        f.polygon[0].0 = 91.0;
        assert!(f.validate().is_err());
        assert_eq!(
            "RTL".parse::<FenceAction>(),
            Ok(FenceAction::ReturnToLaunch)
        );
        assert!("land".parse::<FenceAction>().is_err());
        for a in [
            FenceAction::Report,
            FenceAction::ReturnToLaunch,
            FenceAction::Hold,
        ] {
            assert_eq!(FenceAction::from_ardupilot_param(a.ardupilot_param()), a);
        }
    }
}
