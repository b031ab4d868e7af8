//! Separation between the fleet's vehicles, from their positions. Pure: the service feeds it
//! each position and carries out the holds and releases it returns.
//!
//! Rule (`<separation minDistance holdDistance clearDistance>`): when two vehicles come closer
//! than `holdDistance`, the one of lower priority (the later one in the plan on a tie) holds
//! where it is; it goes on once every other vehicle is farther than `clearDistance` from it (a
//! margin, so a hold does not flicker on the boundary). Closer than `minDistance` is a
//! violation: counted once each time a pair enters it. With `verticalDistance`, two vehicles
//! that far apart in altitude are separated whatever their horizontal distance (aircraft at two
//! altitudes): no hold, no violation, and the closest approach counts only pairs that are not.

use std::collections::HashSet;

use flightplan::geo::{distance, GeoPoint};

use crate::plan::SeparationRule;
use flightplan::fleet_api::SeparationStatus;

/// What the service must do.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Action {
    /// Hold this vehicle (index) where it is.
    Hold(usize),
    /// Let it go on.
    Release(usize),
}

/// The monitor.
#[derive(Clone, Debug)]
pub struct Monitor {
    rule: SeparationRule,
    priorities: Vec<i32>,
    /// Latitude, longitude and altitude above home of each vehicle.
    positions: Vec<Option<(f64, f64, f64)>>,
    held: Vec<bool>,
    violating: HashSet<(usize, usize)>,
    stats: SeparationStatus,
}

impl Monitor {
    /// A monitor for vehicles of these priorities (plan order).
    pub fn new(rule: SeparationRule, priorities: Vec<i32>) -> Self {
        let n = priorities.len();
        Self {
            rule,
            priorities,
            positions: vec![None; n],
            held: vec![false; n],
            violating: HashSet::new(),
            stats: SeparationStatus {
                min_m: rule.min_m,
                ..SeparationStatus::default()
            },
        }
    }

    /// The figures so far.
    pub fn status(&self) -> &SeparationStatus {
        &self.stats
    }

    /// Whether `vehicle` is held.
    pub fn is_held(&self, vehicle: usize) -> bool {
        self.held.get(vehicle).copied().unwrap_or(false)
    }

    /// A new position of `vehicle` (`alt` metres above home); returns the holds and releases
    /// due. Positions that are not numbers are ignored.
    pub fn update(&mut self, vehicle: usize, lat: f64, lon: f64, alt: f64) -> Vec<Action> {
        if vehicle >= self.positions.len() || !lat.is_finite() || !lon.is_finite() {
            return Vec::new();
        }
        let alt = if alt.is_finite() { alt } else { 0.0 };
        self.positions[vehicle] = Some((lat, lon, alt));
        let n = self.positions.len();
        let d = |a: (f64, f64, f64), b: (f64, f64, f64)| {
            distance(GeoPoint::new(a.0, a.1), GeoPoint::new(b.0, b.1))
        };
        let vertical = self.rule.vertical_m;
        let stacked = |a: (f64, f64, f64), b: (f64, f64, f64)| {
            vertical.is_some_and(|v| (a.2 - b.2).abs() >= v)
        };
        let mut out = Vec::new();
        for i in 0..n {
            for j in i + 1..n {
                let (Some(a), Some(b)) = (self.positions[i], self.positions[j]) else {
                    continue;
                };
                if stacked(a, b) {
                    // Apart in altitude: no conflict, whatever their horizontal distance.
                    self.violating.remove(&(i, j));
                    continue;
                }
                let dist = d(a, b);
                if self.stats.closest_m.is_none_or(|c| dist < c) {
                    self.stats.closest_m = Some(dist);
                }
                if dist < self.rule.min_m {
                    if self.violating.insert((i, j)) {
                        self.stats.violations += 1;
                    }
                } else {
                    self.violating.remove(&(i, j));
                }
                if dist < self.rule.hold_m {
                    let lower = if self.priorities[j] <= self.priorities[i] {
                        j
                    } else {
                        i
                    };
                    if !self.held[lower] {
                        self.held[lower] = true;
                        self.stats.holds += 1;
                        out.push(Action::Hold(lower));
                    }
                }
            }
        }
        for v in 0..n {
            if !self.held[v] {
                continue;
            }
            let Some(p) = self.positions[v] else {
                continue;
            };
            let clear = (0..n)
                .filter(|&o| o != v)
                .filter_map(|o| self.positions[o])
                .all(|q| stacked(p, q) || d(p, q) > self.rule.clear_m);
            if clear {
                self.held[v] = false;
                out.push(Action::Release(v));
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Metres east of (41, 1) as a position.
    fn east(m: f64) -> (f64, f64) {
        (41.0, 1.0 + m / (111_320.0 * 41f64.to_radians().cos()))
    }

    #[test]
    fn vehicles_apart_in_altitude_are_separated_whatever_their_distance() {
        let rule = SeparationRule {
            vertical_m: Some(15.0),
            ..rule()
        };
        let mut m = Monitor::new(rule, vec![2, 1]);
        let b = east(3.0);
        // The surveyor at 40 m right above the investigator at 10 m: nothing to do.
        m.update(0, 41.0, 1.0, 40.0);
        assert!(m.update(1, b.0, b.1, 10.0).is_empty());
        assert_eq!((m.status().holds, m.status().violations), (0, 0));
        assert_eq!(m.status().closest_m, None);
        // The investigator climbs to 30 m: 10 m apart in altitude, 3 m across: held, violation.
        assert_eq!(m.update(1, b.0, b.1, 30.0), [Action::Hold(1)]);
        assert_eq!(m.status().violations, 1);
        // Down to 20 m again: 20 m apart in altitude, released.
        assert_eq!(m.update(1, b.0, b.1, 20.0), [Action::Release(1)]);
    }

    fn rule() -> SeparationRule {
        SeparationRule {
            min_m: 5.0,
            hold_m: 15.0,
            clear_m: 20.0,
            vertical_m: None,
        }
    }

    #[test]
    fn the_lower_priority_vehicle_holds_and_goes_on_when_clear() {
        let mut m = Monitor::new(rule(), vec![2, 1]);
        let (a, b) = (east(0.0), east(30.0));
        assert!(m.update(0, a.0, a.1, 0.0).is_empty());
        assert!(m.update(1, b.0, b.1, 0.0).is_empty());
        // The surveyor (priority 2) comes within 14 m: the investigator (1) holds, once.
        let a = east(16.0);
        assert_eq!(m.update(0, a.0, a.1, 0.0), [Action::Hold(1)]);
        assert!(m.update(0, a.0, a.1, 0.0).is_empty());
        assert!(m.is_held(1));
        // 18 m: still inside the clear margin.
        let a = east(12.0);
        assert!(m.update(0, a.0, a.1, 0.0).is_empty());
        // 25 m: released.
        let a = east(5.0);
        assert_eq!(m.update(0, a.0, a.1, 0.0), [Action::Release(1)]);
        let s = m.status();
        assert_eq!((s.holds, s.violations), (1, 0));
        assert!((s.closest_m.unwrap() - 14.0).abs() < 0.1, "{s:?}");
    }

    #[test]
    fn a_violation_is_counted_once_per_entry_and_ties_hold_the_later_vehicle() {
        let mut m = Monitor::new(rule(), vec![0, 0]);
        let b = east(3.0);
        m.update(0, 41.0, 1.0, 0.0);
        assert_eq!(m.update(1, b.0, b.1, 0.0), [Action::Hold(1)]);
        m.update(1, b.0, b.1, 0.0);
        assert_eq!(m.status().violations, 1);
        let b = east(10.0);
        m.update(1, b.0, b.1, 0.0);
        let b = east(4.0);
        m.update(1, b.0, b.1, 0.0);
        assert_eq!(m.status().violations, 2);
        assert!(m.update(7, 41.0, 1.0, 0.0).is_empty());
        assert!(m.update(0, f64::NAN, 1.0, 0.0).is_empty());
    }
}
