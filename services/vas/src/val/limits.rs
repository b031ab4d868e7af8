//! What the VAS accepts from the network before it reaches the autopilot: waypoints with finite
//! coordinates inside the globe and an altitude inside a bound, a bounded number per call and
//! in the queue. A refusal names the waypoint (its index in the call) and the field.

use usal_types::Waypoint;

/// Bounds on the waypoints a `push_waypoints` call may carry.
#[derive(Clone, Debug, PartialEq)]
pub struct WaypointLimits {
    /// Largest |altitude| above home, metres.
    pub max_alt_m: f64,
    /// Largest speed, m/s.
    pub max_speed_mps: f64,
    /// Most waypoints in one call.
    pub max_per_call: usize,
    /// Most waypoints queued (the queue before the call plus the call's).
    pub max_queued: u64,
}

impl Default for WaypointLimits {
    fn default() -> Self {
        Self {
            max_alt_m: 10_000.0,
            max_speed_mps: 100.0,
            max_per_call: 1_000,
            max_queued: 100_000,
        }
    }
}

impl WaypointLimits {
    /// Checks `wps` against the limits (the queue's room is the APL's to check, as it queues
    /// them: [`crate::apl::check_room`]).
    ///
    /// # Errors
    /// The first violation, as the caller reads it: `waypoint 3 (seq 12): lat 91 not in
    /// [-90, 90]`.
    pub fn check(&self, wps: &[Waypoint]) -> Result<(), String> {
        if wps.len() > self.max_per_call {
            return Err(format!(
                "{} waypoints in one call: at most {}",
                wps.len(),
                self.max_per_call
            ));
        }
        for (i, w) in wps.iter().enumerate() {
            let fields = [
                ("lat", w.lat, 90.0),
                ("lon", w.lon, 180.0),
                ("alt", w.alt, self.max_alt_m),
            ];
            for (name, v, bound) in fields {
                if !v.is_finite() || v.abs() > bound {
                    return Err(format!(
                        "waypoint {i} (seq {}): {name} {v} not in [-{bound}, {bound}]",
                        w.seq
                    ));
                }
            }
            if !(w.speed.is_finite() && (0.0..=self.max_speed_mps).contains(&w.speed)) {
                return Err(format!(
                    "waypoint {i} (seq {}): speed {} not in [0, {}]",
                    w.seq, w.speed, self.max_speed_mps
                ));
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn wp(lat: f64, lon: f64, alt: f64) -> Waypoint {
        Waypoint {
            seq: 7,
            lat,
            lon,
            alt,
            ..Waypoint::default()
        }
    }

    #[test]
    fn bad_coordinates_are_refused_naming_the_index_and_field() {
        let l = WaypointLimits::default();
        assert!(l
            .check(&[wp(41.0, 2.0, 10.0), wp(-90.0, 180.0, -10.0)])
            .is_ok());
        let cases = [
            (wp(91.0, 0.0, 0.0), "waypoint 1 (seq 7): lat 91"),
            (wp(0.0, -180.5, 0.0), "waypoint 1 (seq 7): lon -180.5"),
            (wp(f64::NAN, 0.0, 0.0), "waypoint 1 (seq 7): lat NaN"),
            (wp(0.0, f64::INFINITY, 0.0), "waypoint 1 (seq 7): lon inf"),
            (wp(0.0, 0.0, 10_001.0), "waypoint 1 (seq 7): alt 10001"),
        ];
        for (bad, msg) in cases {
            let e = l.check(&[wp(0.0, 0.0, 0.0), bad]).unwrap_err();
            assert!(e.starts_with(msg), "{e}");
        }
        let mut fast = wp(0.0, 0.0, 0.0);
        fast.speed = f64::NAN;
        assert!(l.check(&[fast]).unwrap_err().contains("speed NaN"));
    }

    #[test]
    fn counts_are_capped_per_call_and_in_the_queue() {
        let l = WaypointLimits {
            max_per_call: 3,
            max_queued: 5,
            ..WaypointLimits::default()
        };
        let four = vec![wp(0.0, 0.0, 0.0); 4];
        assert!(l.check(&four).unwrap_err().contains("at most 3"));
        assert!(l.check(&four[..3]).is_ok());
        // The queue's room, checked by the APL with the push.
        use crate::apl::check_room;
        assert!(check_room(2, 3, l.max_queued).is_ok());
        let e = check_room(3, 3, l.max_queued).unwrap_err().to_string();
        assert!(e.contains("at most 5 queued"), "{e}");
        assert_eq!(e, "3 queued + 3 pushed = 6 waypoints: at most 5 queued");
        assert!(
            check_room(u64::MAX, 1, l.max_queued).is_err(),
            "no overflow"
        );
    }
}
