//! The Broz investigator's choice (seed 002): the next point to visit is the pending one
//! nearest to where the vehicle is now, so the tour is built in nearest-neighbour order as
//! detections arrive. Pure.

use flightplan::geo::{distance, GeoPoint};

/// The index in `pending` of the point to visit next from `here`: the nearest one that is not
/// within `keep_off_m` of any of `others` (another vehicle's position: going there would only
/// end in a separation hold). `None` when there is none.
pub fn next_target(
    here: (f64, f64),
    pending: &[(f64, f64)],
    others: &[(f64, f64)],
    keep_off_m: f64,
) -> Option<usize> {
    let at = |p: (f64, f64)| GeoPoint::new(p.0, p.1);
    pending
        .iter()
        .enumerate()
        .filter(|(_, p)| {
            others
                .iter()
                .all(|o| distance(at(**p), at(*o)) >= keep_off_m)
        })
        .map(|(i, p)| (i, distance(at(here), at(*p))))
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i)
}

/// The whole nearest-neighbour tour of `points` from `start` (indices), as [`next_target`]
/// would visit them with nothing else around.
pub fn tour(start: (f64, f64), points: &[(f64, f64)]) -> Vec<usize> {
    let mut left: Vec<usize> = (0..points.len()).collect();
    let mut here = start;
    let mut out = Vec::new();
    while !left.is_empty() {
        let pts: Vec<(f64, f64)> = left.iter().map(|&i| points[i]).collect();
        let Some(k) = next_target(here, &pts, &[], 0.0) else {
            break;
        };
        let i = left.remove(k);
        here = points[i];
        out.push(i);
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_tour_goes_to_the_nearest_point_each_time() {
        // Along a line east of the start: 1 m, 3 m... apart in longitude degrees' terms.
        let pts = [
            (41.0, 1.0004),
            (41.0, 1.0001),
            (41.0, 1.0009),
            (41.0, 1.0002),
        ];
        assert_eq!(tour((41.0, 1.0), &pts), [1, 3, 0, 2]);
        // From the far end the order reverses.
        assert_eq!(tour((41.0, 1.001), &pts), [2, 0, 3, 1]);
        assert!(tour((41.0, 1.0), &[]).is_empty());
    }

    #[test]
    fn points_near_another_vehicle_wait() {
        let pts = [(41.0, 1.0001), (41.0, 1.0005)];
        // The nearer point is 2 m from the other vehicle: the farther one is chosen.
        assert_eq!(
            next_target((41.0, 1.0), &pts, &[(41.0, 1.000_12)], 15.0),
            Some(1)
        );
        // Both near it: none.
        assert_eq!(
            next_target((41.0, 1.0), &pts, &[(41.0, 1.0003)], 40.0),
            None
        );
    }
}
