//! The operator's edits to the points the investigators visit (the fleet's `edit_points`):
//! add a point of their own, delete one, put some first. Pure: on the fleet's detections and
//! the order the operator gave; the fleet service applies the outcome.

use std::collections::HashSet;

use flightplan::fleet_api::{Detection, PointEdit, OPERATOR};

use crate::wavefront::{self, Obstacle};

/// The points and the operator's order, as the fleet holds them.
pub struct Points<'a> {
    /// Every point reported or added, in report order.
    pub detections: &'a mut Vec<Detection>,
    /// The pending points to visit first, in order.
    pub visit_first: &'a mut Vec<(String, u32)>,
}

/// Whether a point is still to be visited.
pub fn pending(d: &Detection) -> bool {
    d.visited.is_none() && !d.deleted
}

impl Points<'_> {
    fn find(&self, by: &str, id: u32) -> Result<usize, String> {
        self.detections
            .iter()
            .position(|d| d.by == by && d.id == id)
            .ok_or_else(|| format!("no point #{id} reported by {by}"))
    }

    /// Applies `edit`; `claimed` are the points an investigator is on its way to, `at_s` the
    /// fleet plan's time. Answers in words, or says why the edit is refused.
    pub fn apply(
        &mut self,
        edit: PointEdit,
        obstacles: &[Obstacle],
        claimed: &HashSet<usize>,
        at_s: f64,
    ) -> Result<String, String> {
        match edit {
            PointEdit::Add { lat, lon } => {
                // (NaN is in no range.)
                if !((-90.0..=90.0).contains(&lat) && (-180.0..=180.0).contains(&lon)) {
                    return Err(format!("({lat}, {lon}) is not a position"));
                }
                if let Some(o) = obstacles
                    .iter()
                    .find(|o| wavefront::contains(o, (lat, lon)))
                {
                    return Err(format!(
                        "({lat:.7}, {lon:.7}) is inside obstacle `{}`: no investigator can \
                         visit it",
                        o.name
                    ));
                }
                let id = self
                    .detections
                    .iter()
                    .filter(|d| d.by == OPERATOR)
                    .map(|d| d.id)
                    .max()
                    .unwrap_or(0)
                    + 1;
                self.detections.push(Detection {
                    id,
                    by: OPERATOR.to_owned(),
                    lat,
                    lon,
                    confidence: 1.0,
                    at_s,
                    visited: None,
                    deleted: false,
                });
                Ok(format!("point #{id} added at {lat:.7}, {lon:.7}"))
            }
            PointEdit::Delete { by, id } => {
                let k = self.find(&by, id)?;
                let d = &mut self.detections[k];
                if let Some((who, _)) = &d.visited {
                    return Err(format!("#{id} of {by} was already visited by {who}"));
                }
                if d.deleted {
                    return Ok(format!("#{id} of {by} was deleted already"));
                }
                d.deleted = true;
                self.visit_first.retain(|(b, i)| !(b == &by && *i == id));
                Ok(if claimed.contains(&k) {
                    format!(
                        "#{id} of {by} deleted; the visit under way there is finished, no other \
                         follows"
                    )
                } else {
                    format!("#{id} of {by} deleted")
                })
            }
            PointEdit::Order { points } => {
                let mut seen = HashSet::new();
                for (by, id) in &points {
                    let k = self.find(by, *id)?;
                    if !pending(&self.detections[k]) {
                        return Err(format!("#{id} of {by} is not waiting for a visit"));
                    }
                    if !seen.insert((by.clone(), *id)) {
                        return Err(format!("#{id} of {by} is named twice"));
                    }
                }
                let text: Vec<String> = points.iter().map(|(b, i)| format!("#{i} {b}")).collect();
                *self.visit_first = points;
                Ok(if text.is_empty() {
                    "no point first: nearest first".to_owned()
                } else {
                    format!("visiting first: {}", text.join(", "))
                })
            }
        }
    }

    /// The first point of the operator's order that is pending and `free` (not claimed), if
    /// any; points of the order no longer pending are dropped from it.
    pub fn first_ordered(&mut self, free: impl Fn(usize) -> bool) -> Option<usize> {
        let detections = &*self.detections;
        let index =
            |(by, id): &(String, u32)| detections.iter().position(|d| &d.by == by && d.id == *id);
        self.visit_first
            .retain(|p| index(p).is_some_and(|k| pending(&detections[k])));
        self.visit_first.iter().filter_map(index).find(|&k| free(k))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn det(by: &str, id: u32, lat: f64) -> Detection {
        Detection {
            id,
            by: by.into(),
            lat,
            lon: 2.0,
            confidence: 0.5,
            at_s: 1.0,
            visited: None,
            deleted: false,
        }
    }

    fn shed() -> Obstacle {
        Obstacle {
            name: "shed".into(),
            height_m: 6.0,
            polygon: vec![(41.0, 2.0), (41.0, 2.001), (41.001, 2.001), (41.001, 2.0)],
        }
    }

    #[test]
    fn the_operator_adds_points_of_their_own_but_not_inside_an_obstacle() {
        let (mut dets, mut first) = (vec![det("surveyor", 1, 40.0)], vec![]);
        let mut p = Points {
            detections: &mut dets,
            visit_first: &mut first,
        };
        let none = HashSet::new();
        let add = |lat, lon| PointEdit::Add { lat, lon };
        assert_eq!(
            p.apply(add(40.5, 2.0), &[shed()], &none, 3.0),
            Ok("point #1 added at 40.5000000, 2.0000000".into())
        );
        assert!(p.apply(add(40.6, 2.0), &[shed()], &none, 4.0).is_ok());
        let e = p
            .apply(add(41.0005, 2.0005), &[shed()], &none, 5.0)
            .unwrap_err();
        assert!(e.contains("inside obstacle `shed`"), "{e}");
        assert!(p.apply(add(f64::NAN, 2.0), &[], &none, 5.0).is_err());
        assert!(p.apply(add(95.0, 2.0), &[], &none, 5.0).is_err());
        let ops: Vec<(u32, f32)> = dets
            .iter()
            .filter(|d| d.by == OPERATOR)
            .map(|d| (d.id, d.confidence))
            .collect();
        assert_eq!(ops, [(1, 1.0), (2, 1.0)]);
    }

    #[test]
    fn a_deleted_point_is_not_visited_and_leaves_the_order() {
        let mut dets = vec![det("surveyor", 1, 40.0), det("surveyor", 2, 40.1)];
        dets[1].visited = Some(("investigator".into(), 9.0));
        let mut first = vec![("surveyor".to_owned(), 1)];
        let mut p = Points {
            detections: &mut dets,
            visit_first: &mut first,
        };
        let del = |id| PointEdit::Delete {
            by: "surveyor".into(),
            id,
        };
        let claimed = HashSet::from([0]);
        let said = p.apply(del(1), &[], &claimed, 0.0).unwrap();
        assert!(said.contains("visit under way"), "{said}");
        assert!(p
            .apply(del(2), &[], &claimed, 0.0)
            .unwrap_err()
            .contains("already visited"));
        assert!(p
            .apply(del(7), &[], &claimed, 0.0)
            .unwrap_err()
            .contains("no point #7"));
        assert!(first.is_empty());
        assert!(dets[0].deleted && !pending(&dets[0]));
    }

    #[test]
    fn the_operators_order_comes_first_and_forgets_points_visited_since() {
        let mut dets = vec![
            det("surveyor", 1, 40.0),
            det("surveyor", 2, 40.1),
            det("surveyor", 3, 40.2),
        ];
        let mut first = vec![];
        let mut p = Points {
            detections: &mut dets,
            visit_first: &mut first,
        };
        let none = HashSet::new();
        let order = |ids: &[u32]| PointEdit::Order {
            points: ids.iter().map(|i| ("surveyor".to_owned(), *i)).collect(),
        };
        assert!(p.apply(order(&[3, 1]), &[], &none, 0.0).is_ok());
        assert_eq!(p.first_ordered(|_| true), Some(2));
        // Claimed by another investigator: the next of the order.
        assert_eq!(p.first_ordered(|k| k != 2), Some(0));
        p.detections[2].visited = Some(("investigator".into(), 5.0));
        assert_eq!(p.first_ordered(|_| true), Some(0));
        assert_eq!(p.visit_first.len(), 1, "the visited point left the order");
        // Named twice, or not pending: refused, the order kept.
        assert!(p.apply(order(&[1, 1]), &[], &none, 0.0).is_err());
        assert!(p.apply(order(&[3]), &[], &none, 0.0).is_err());
        assert_eq!(p.visit_first.len(), 1);
        // An empty order: nearest first again.
        assert!(p.apply(order(&[]), &[], &none, 0.0).is_ok());
        assert_eq!(p.first_ordered(|_| true), None);
    }
}
