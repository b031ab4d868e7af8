//! The obstacle-aware route of a visit (seed 002: Broz's investigator flies around what stands
//! in its way): a static obstacle map, polygons with heights, and a wavefront planner over a
//! grid of it. Pure.
//!
//! The wave spreads from the goal over the free cells (8-connected, diagonal steps cost √2), so
//! every free cell holds its distance to the goal; the route descends it from the start, then
//! keeps only the turns (a point is dropped where the straight line past it stays clear). An
//! obstacle counts where it reaches within [`CLEARANCE_M`] below the flight altitude, and is
//! inflated by the same clearance horizontally.

use flightplan::geo::{GeoPoint, LocalFrame, Xy};

/// Kept between the route and an obstacle, horizontally and vertically, metres.
pub const CLEARANCE_M: f64 = 5.0;
/// The grid's cell, metres.
pub const CELL_M: f64 = 2.5;
/// The grid's largest side, cells (a 5 km square at [`CELL_M`]); a longer visit is flown
/// straight when nothing stands on its line, else refused.
pub const MAX_CELLS: usize = 2000;

/// A static obstacle: an area (a closed polygon) and how tall it stands above home.
#[derive(Clone, Debug, PartialEq)]
pub struct Obstacle {
    /// Its name, for messages.
    pub name: String,
    /// Its outline, `(lat, lon)` degrees, at least 3 points (closed implicitly).
    pub polygon: Vec<(f64, f64)>,
    /// Its height above home, metres.
    pub height_m: f64,
}

/// Why no route was found.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum RouteError {
    /// The start or the goal is inside an obstacle.
    #[error("{what} is inside obstacle `{obstacle}`")]
    Inside {
        /// `the start` or `the goal`.
        what: &'static str,
        /// The obstacle.
        obstacle: String,
    },
    /// Obstacles wall the goal off.
    #[error("no way around the obstacles from the start to the goal")]
    Walled,
    /// Farther apart than the grid covers, and something on the straight line.
    #[error("the visit is longer than the planner's grid ({} m), and an obstacle is on its line", MAX_CELLS as f64 * CELL_M)]
    TooFar,
}

/// The route from `start` to `goal` at `alt_m` above home around `obstacles`: the points to
/// fly through after `start`, `goal` last (just `[goal]` when the straight line is clear).
///
/// # Errors
/// The start or the goal inside an obstacle, no way around, or too far for the grid.
pub fn route(
    start: (f64, f64),
    goal: (f64, f64),
    alt_m: f64,
    obstacles: &[Obstacle],
) -> Result<Vec<(f64, f64)>, RouteError> {
    let frame = LocalFrame::new(GeoPoint::new(start.0, start.1));
    let local = |p: (f64, f64)| frame.to_local(GeoPoint::new(p.0, p.1));
    // Only what reaches near the flight altitude is in the way.
    let walls: Vec<(String, Vec<Xy>)> = obstacles
        .iter()
        .filter(|o| o.height_m + CLEARANCE_M > alt_m)
        .map(|o| {
            (
                o.name.clone(),
                o.polygon.iter().map(|p| local(*p)).collect(),
            )
        })
        .collect();
    let (s, g) = (local(start), local(goal));
    for (what, p) in [("the start", s), ("the goal", g)] {
        if let Some((name, _)) = walls.iter().find(|(_, w)| inside(p, w)) {
            return Err(RouteError::Inside {
                what,
                obstacle: name.clone(),
            });
        }
    }
    let blocked = |a: Xy, b: Xy| walls.iter().any(|(_, w)| segment_blocked(a, b, w));
    if !blocked(s, g) {
        return Ok(vec![goal]);
    }
    let grid = Grid::around(&[s, g], &walls).ok_or(RouteError::TooFar)?;
    // A start or goal closer to an obstacle than the clearance (a point of interest beside a
    // wall, a vehicle that stopped there) keeps a way out: near it only the obstacle itself
    // is blocked.
    let near_end = |c: Xy| {
        [s, g]
            .iter()
            .any(|e| (c.e - e.e).hypot(c.n - e.n) < CLEARANCE_M + CELL_M)
    };
    let free: Vec<bool> = (0..grid.w * grid.h)
        .map(|i| {
            let c = grid.centre(i % grid.w, i / grid.w);
            !walls.iter().any(|(_, w)| {
                if near_end(c) {
                    inside(c, w)
                } else {
                    near_or_inside(c, w)
                }
            })
        })
        .collect();
    let cost = grid.wave(&free, grid.cell_of(g));
    let mut at = grid.cell_of(s);
    if cost[at.1 * grid.w + at.0] == u32::MAX {
        return Err(RouteError::Walled);
    }
    // Down the wave, cell by cell, to the goal.
    let mut cells = vec![s];
    while cost[at.1 * grid.w + at.0] > 0 {
        let next = grid
            .neighbours(at)
            .filter(|&(x, y)| free[y * grid.w + x])
            .min_by_key(|&(x, y)| cost[y * grid.w + x])
            .ok_or(RouteError::Walled)?;
        at = next;
        cells.push(grid.centre(at.0, at.1));
    }
    cells.push(g);
    // The turns alone: from each kept point, as far along as the line stays clear.
    let mut out = Vec::new();
    let mut from = 0;
    while from + 1 < cells.len() {
        let mut to = cells.len() - 1;
        while to > from + 1 && blocked(cells[from], cells[to]) {
            to -= 1;
        }
        out.push(cells[to]);
        from = to;
    }
    let n = out.len();
    Ok(out
        .iter()
        .enumerate()
        .map(|(i, p)| {
            if i + 1 == n {
                goal
            } else {
                let g = frame.to_geo(*p);
                (g.lat, g.lon)
            }
        })
        .collect())
}

/// Whether `p` (`(lat, lon)`) is inside obstacle `o`'s outline (no clearance).
pub fn contains(o: &Obstacle, p: (f64, f64)) -> bool {
    let Some(&first) = o.polygon.first() else {
        return false;
    };
    let frame = LocalFrame::new(GeoPoint::new(first.0, first.1));
    let local = |q: (f64, f64)| frame.to_local(GeoPoint::new(q.0, q.1));
    let w: Vec<Xy> = o.polygon.iter().map(|q| local(*q)).collect();
    inside(local(p), &w)
}

/// Whether `p` is inside polygon `w` or within [`CLEARANCE_M`] of its outline.
fn near_or_inside(p: Xy, w: &[Xy]) -> bool {
    inside(p, w) || edges(w).any(|(a, b)| distance_to_segment(p, a, b) < CLEARANCE_M)
}

/// Whether the segment `a`-`b` passes within [`CLEARANCE_M`] of polygon `w` (or through it).
fn segment_blocked(a: Xy, b: Xy, w: &[Xy]) -> bool {
    if near_or_inside(a, w) || near_or_inside(b, w) {
        return true;
    }
    // Sampled along at a fraction of the clearance: exact enough for metres-wide margins.
    let len = (b.e - a.e).hypot(b.n - a.n);
    let n = (len / (CLEARANCE_M / 2.0)).ceil().max(1.0) as usize;
    (1..n).any(|i| {
        let t = i as f64 / n as f64;
        near_or_inside(Xy::new(a.e + (b.e - a.e) * t, a.n + (b.n - a.n) * t), w)
    })
}

fn edges(w: &[Xy]) -> impl Iterator<Item = (Xy, Xy)> + '_ {
    w.iter()
        .zip(w.iter().cycle().skip(1))
        .map(|(a, b)| (*a, *b))
}

/// Even-odd rule.
fn inside(p: Xy, w: &[Xy]) -> bool {
    let mut c = false;
    for (a, b) in edges(w) {
        if (a.n > p.n) != (b.n > p.n) && p.e < (b.e - a.e) * (p.n - a.n) / (b.n - a.n) + a.e {
            c = !c;
        }
    }
    c
}

fn distance_to_segment(p: Xy, a: Xy, b: Xy) -> f64 {
    let (dx, dy) = (b.e - a.e, b.n - a.n);
    let len2 = dx * dx + dy * dy;
    let t = if len2 == 0.0 {
        0.0
    } else {
        (((p.e - a.e) * dx + (p.n - a.n) * dy) / len2).clamp(0.0, 1.0)
    };
    (p.e - (a.e + t * dx)).hypot(p.n - (a.n + t * dy))
}

/// A grid of [`CELL_M`] cells in the local frame.
struct Grid {
    x0: f64,
    y0: f64,
    w: usize,
    h: usize,
}

impl Grid {
    /// Around the points and the walls, with room to go round them; `None` past
    /// [`MAX_CELLS`].
    fn around(points: &[Xy], walls: &[(String, Vec<Xy>)]) -> Option<Self> {
        let all = points
            .iter()
            .chain(walls.iter().flat_map(|(_, w)| w.iter()));
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        for p in all {
            x0 = x0.min(p.e);
            y0 = y0.min(p.n);
            x1 = x1.max(p.e);
            y1 = y1.max(p.n);
        }
        let margin = 4.0 * CLEARANCE_M;
        let (x0, y0) = (x0 - margin, y0 - margin);
        let w = ((x1 + margin - x0) / CELL_M).ceil() as usize + 1;
        let h = ((y1 + margin - y0) / CELL_M).ceil() as usize + 1;
        (w <= MAX_CELLS && h <= MAX_CELLS).then_some(Self { x0, y0, w, h })
    }

    fn centre(&self, x: usize, y: usize) -> Xy {
        Xy::new(
            self.x0 + (x as f64 + 0.5) * CELL_M,
            self.y0 + (y as f64 + 0.5) * CELL_M,
        )
    }

    fn cell_of(&self, p: Xy) -> (usize, usize) {
        let x = ((p.e - self.x0) / CELL_M).floor().max(0.0) as usize;
        let y = ((p.n - self.y0) / CELL_M).floor().max(0.0) as usize;
        (x.min(self.w - 1), y.min(self.h - 1))
    }

    fn neighbours(&self, (x, y): (usize, usize)) -> impl Iterator<Item = (usize, usize)> + '_ {
        (-1i64..=1)
            .flat_map(|dy| (-1i64..=1).map(move |dx| (dx, dy)))
            .filter(|&d| d != (0, 0))
            .filter_map(move |(dx, dy)| {
                let nx = x as i64 + dx;
                let ny = y as i64 + dy;
                (nx >= 0 && ny >= 0 && (nx as usize) < self.w && (ny as usize) < self.h)
                    .then_some((nx as usize, ny as usize))
            })
    }

    /// The wave from `goal` over the free cells: each cell's cost to the goal (10 a side
    /// step, 14 a diagonal one; `u32::MAX`: unreachable). The goal's own cell counts as free.
    fn wave(&self, free: &[bool], goal: (usize, usize)) -> Vec<u32> {
        use std::cmp::Reverse;
        use std::collections::BinaryHeap;
        let mut cost = vec![u32::MAX; self.w * self.h];
        let mut heap = BinaryHeap::new();
        cost[goal.1 * self.w + goal.0] = 0;
        heap.push(Reverse((0u32, goal)));
        while let Some(Reverse((c, at))) = heap.pop() {
            if c > cost[at.1 * self.w + at.0] {
                continue;
            }
            for n in self.neighbours(at) {
                let i = n.1 * self.w + n.0;
                if !free[i] {
                    continue;
                }
                let step = if n.0 != at.0 && n.1 != at.1 { 14 } else { 10 };
                if c + step < cost[i] {
                    cost[i] = c + step;
                    heap.push(Reverse((c + step, n)));
                }
            }
        }
        cost
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const HOME: (f64, f64) = (41.275, 1.987);

    /// `(north, east)` metres from home as `(lat, lon)`.
    fn at(north: f64, east: f64) -> (f64, f64) {
        let f = LocalFrame::new(GeoPoint::new(HOME.0, HOME.1));
        let g = f.to_geo(Xy::new(east, north));
        (g.lat, g.lon)
    }

    fn metres(p: (f64, f64)) -> Xy {
        LocalFrame::new(GeoPoint::new(HOME.0, HOME.1)).to_local(GeoPoint::new(p.0, p.1))
    }

    /// A wall 20 m wide (east-west) and 6 m deep, 30 m tall, 50 m north of home.
    fn wall(height_m: f64) -> Obstacle {
        Obstacle {
            name: "hangar".into(),
            polygon: vec![
                at(47.0, -10.0),
                at(47.0, 10.0),
                at(53.0, 10.0),
                at(53.0, -10.0),
            ],
            height_m,
        }
    }

    #[test]
    fn a_clear_line_is_flown_straight() {
        let r = route(HOME, at(100.0, 0.0), 20.0, &[]).unwrap();
        assert_eq!(r, vec![at(100.0, 0.0)]);
        // Flying well above the wall: straight too.
        let r = route(HOME, at(100.0, 0.0), 50.0, &[wall(30.0)]).unwrap();
        assert_eq!(r.len(), 1);
    }

    #[test]
    fn the_route_goes_round_a_wall_keeping_clear_of_it() {
        let goal = at(100.0, 0.0);
        let r = route(HOME, goal, 20.0, &[wall(30.0)]).unwrap();
        assert!(r.len() >= 2, "{r:?}");
        assert_eq!(*r.last().unwrap(), goal);
        // Every leg of the route stays clear of the wall, by the clearance (within a cell).
        let w: Vec<Xy> = wall(30.0).polygon.iter().map(|p| metres(*p)).collect();
        let mut prev = metres(HOME);
        for p in &r {
            let q = metres(*p);
            for i in 0..=100 {
                let t = f64::from(i) / 100.0;
                let s = Xy::new(prev.e + (q.e - prev.e) * t, prev.n + (q.n - prev.n) * t);
                assert!(!inside(s, &w), "through the wall at {s:?}");
                let d = edges(&w)
                    .map(|(a, b)| distance_to_segment(s, a, b))
                    .fold(f64::MAX, f64::min);
                assert!(d > CLEARANCE_M - CELL_M, "{d:.1} m from the wall at {s:?}");
            }
            prev = q;
        }
        // Round the end of a 20 m wall, not a long detour: under 130 m flown for 100 m.
        let mut len = 0.0;
        let mut prev = metres(HOME);
        for p in &r {
            let q = metres(*p);
            len += (q.e - prev.e).hypot(q.n - prev.n);
            prev = q;
        }
        assert!(len < 130.0, "{len:.0} m: {r:?}");
    }

    #[test]
    fn a_goal_beside_a_wall_is_reached_from_its_side() {
        // 2 m south of the wall, closer than the clearance: reached, never through the wall.
        let goal = at(45.0, 0.0);
        let r = route(HOME, goal, 0.0, &[wall(30.0)]).unwrap();
        assert_eq!(*r.last().unwrap(), goal);
        let w: Vec<Xy> = wall(30.0).polygon.iter().map(|p| metres(*p)).collect();
        assert!(r.iter().all(|p| !inside(metres(*p), &w)), "{r:?}");
        // And from there on to the far side, round the wall.
        let r = route(goal, at(60.0, 0.0), 0.0, &[wall(30.0)]).unwrap();
        assert!(r.len() >= 2, "{r:?}");
    }

    #[test]
    fn a_goal_inside_or_walled_off_is_refused_with_the_reason() {
        let e = route(HOME, at(50.0, 0.0), 20.0, &[wall(30.0)]).unwrap_err();
        assert_eq!(
            e,
            RouteError::Inside {
                what: "the goal",
                obstacle: "hangar".into()
            }
        );
        // A ring round the goal: walled off.
        let ring = |n: f64, e: f64, name: &str| Obstacle {
            name: name.into(),
            polygon: vec![
                at(n - 4.0, e - 4.0),
                at(n - 4.0, e + 4.0),
                at(n + 4.0, e + 4.0),
                at(n + 4.0, e - 4.0),
            ],
            height_m: 100.0,
        };
        let walls: Vec<Obstacle> = [
            (-12.0, -12.0),
            (-12.0, 0.0),
            (-12.0, 12.0),
            (0.0, 12.0),
            (12.0, 12.0),
            (12.0, 0.0),
            (12.0, -12.0),
            (0.0, -12.0),
        ]
        .iter()
        .enumerate()
        .map(|(i, (n, e))| ring(100.0 + n, e + 0.0, &format!("r{i}")))
        .collect();
        let e = route(HOME, at(100.0, 0.0), 20.0, &walls).unwrap_err();
        assert_eq!(e, RouteError::Walled);
    }
}
