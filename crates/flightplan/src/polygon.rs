//! Planar polygon helpers in a local frame: centroid frame, self-intersection test, inward
//! offset. Shared by validation and pattern generation.

use crate::geo::{GeoPoint, LocalFrame, Xy};

/// The frame a polygon's pattern is computed in: origin at the vertex mean.
pub fn polygon_frame(poly: &[GeoPoint]) -> LocalFrame {
    let n = poly.len().max(1) as f64;
    let lat = poly.iter().map(|p| p.lat).sum::<f64>() / n;
    let lon = poly.iter().map(|p| p.lon).sum::<f64>() / n;
    LocalFrame::new(GeoPoint::new(lat, lon))
}

/// Most vertices a polygon may have: validation and pattern generation compare every edge with
/// every other, so the work grows with the square of this.
pub const MAX_VERTICES: usize = 1000;

/// The unit vector left of `bearing` (degrees true).
pub fn left_of(bearing: f64) -> Xy {
    let d = Xy::unit(bearing);
    Xy::new(-d.n, d.e)
}

/// The polygon's extent across tracks flown along `bearing`: the distance between the two
/// outermost tracks' borders.
pub fn width_across(pts: &[Xy], bearing: f64) -> f64 {
    let left = left_of(bearing);
    let (lo, hi) = pts
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
            let v = p.dot(left);
            (lo.min(v), hi.max(v))
        });
    hi - lo
}

/// The bearing whose perpendicular width of the polygon is smallest, tried along each edge
/// (for a convex polygon the optimum is parallel to an edge).
pub fn auto_sweep(pts: &[Xy]) -> f64 {
    let n = pts.len();
    let mut best = (f64::INFINITY, 0.0);
    for i in 0..n {
        let e = pts[(i + 1) % n].minus(pts[i]);
        if e.norm() < 1e-9 {
            continue;
        }
        let b = e.bearing() % 180.0;
        let w = width_across(pts, b);
        if w < best.0 - 1e-9 {
            best = (w, b);
        }
    }
    best.1
}

/// Signed area (positive anticlockwise, i.e. east→north).
pub fn signed_area(pts: &[Xy]) -> f64 {
    let n = pts.len();
    (0..n).map(|i| pts[i].cross(pts[(i + 1) % n])).sum::<f64>() / 2.0
}

fn orient(a: Xy, b: Xy, c: Xy) -> f64 {
    b.minus(a).cross(c.minus(a))
}

fn on_segment(a: Xy, b: Xy, p: Xy) -> bool {
    p.e >= a.e.min(b.e) - 1e-9
        && p.e <= a.e.max(b.e) + 1e-9
        && p.n >= a.n.min(b.n) - 1e-9
        && p.n <= a.n.max(b.n) + 1e-9
}

/// Whether closed segments `ab` and `cd` share a point.
pub fn segments_intersect(a: Xy, b: Xy, c: Xy, d: Xy) -> bool {
    let (d1, d2, d3, d4) = (
        orient(c, d, a),
        orient(c, d, b),
        orient(a, b, c),
        orient(a, b, d),
    );
    if ((d1 > 0.0 && d2 < 0.0) || (d1 < 0.0 && d2 > 0.0))
        && ((d3 > 0.0 && d4 < 0.0) || (d3 < 0.0 && d4 > 0.0))
    {
        return true;
    }
    (d1 == 0.0 && on_segment(c, d, a))
        || (d2 == 0.0 && on_segment(c, d, b))
        || (d3 == 0.0 && on_segment(a, b, c))
        || (d4 == 0.0 && on_segment(a, b, d))
}

/// The first pair of edges (0-based, edge i runs from vertex i to i+1) that cross, if any.
/// Adjacent edges share a vertex by construction and are not compared.
pub fn self_intersection(pts: &[Xy]) -> Option<(usize, usize)> {
    let n = pts.len();
    for i in 0..n {
        for j in (i + 1)..n {
            let adjacent = j == i + 1 || (i == 0 && j == n - 1);
            if adjacent {
                continue;
            }
            if segments_intersect(pts[i], pts[(i + 1) % n], pts[j], pts[(j + 1) % n]) {
                return Some((i, j));
            }
        }
    }
    None
}

/// The polygon moved inward by `d` (mitred corners). `None` when the ring collapses or turns
/// inside out, which ends a perimeter pattern.
pub fn inset(pts: &[Xy], d: f64) -> Option<Vec<Xy>> {
    let n = pts.len();
    if n < 3 {
        return None;
    }
    let area = signed_area(pts);
    // Inward normal: left of each edge for an anticlockwise ring, right for a clockwise one.
    let side = if area > 0.0 { 1.0 } else { -1.0 };
    let lines: Vec<(Xy, Xy)> = (0..n)
        .map(|i| {
            let a = pts[i];
            let b = pts[(i + 1) % n];
            let dir = b.minus(a).scale(1.0 / b.minus(a).norm().max(1e-12));
            let normal = Xy::new(-dir.n, dir.e).scale(side);
            (a.plus(normal.scale(d)), dir)
        })
        .collect();
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let (p1, d1) = lines[(i + n - 1) % n];
        let (p2, d2) = lines[i];
        let den = d1.cross(d2);
        if den.abs() < 1e-9 {
            out.push(p2);
            continue;
        }
        let t = p2.minus(p1).cross(d2) / den;
        out.push(p1.plus(d1.scale(t)));
    }
    // An edge that flipped direction means the offset passed through a collapse.
    for i in 0..n {
        let before = pts[(i + 1) % n].minus(pts[i]);
        let after = out[(i + 1) % n].minus(out[i]);
        if before.dot(after) <= 0.0 {
            return None;
        }
    }
    let new_area = signed_area(&out);
    if new_area * area <= 0.0 || new_area.abs() < 1e-6 || self_intersection(&out).is_some() {
        return None;
    }
    // A mitred inset of a valid ring can stay simple yet poke outside; require every vertex inside.
    if out.iter().any(|p| !contains(pts, *p)) {
        return None;
    }
    Some(out)
}

/// Even-odd point-in-polygon test.
pub fn contains(pts: &[Xy], p: Xy) -> bool {
    let n = pts.len();
    let mut inside = false;
    for i in 0..n {
        let (a, b) = (pts[i], pts[(i + 1) % n]);
        if (a.n > p.n) != (b.n > p.n) {
            let x = a.e + (p.n - a.n) / (b.n - a.n) * (b.e - a.e);
            if p.e < x {
                inside = !inside;
            }
        }
    }
    inside
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bow_tie_self_intersects_and_square_does_not() {
        let sq = [
            Xy::new(0.0, 0.0),
            Xy::new(10.0, 0.0),
            Xy::new(10.0, 10.0),
            Xy::new(0.0, 10.0),
        ];
        assert_eq!(self_intersection(&sq), None);
        let bow = [
            Xy::new(0.0, 0.0),
            Xy::new(10.0, 10.0),
            Xy::new(10.0, 0.0),
            Xy::new(0.0, 10.0),
        ];
        assert_eq!(self_intersection(&bow), Some((0, 2)));
    }

    #[test]
    fn inset_square_and_collapse() {
        let sq = [
            Xy::new(0.0, 0.0),
            Xy::new(10.0, 0.0),
            Xy::new(10.0, 10.0),
            Xy::new(0.0, 10.0),
        ];
        let r = inset(&sq, 2.0).unwrap();
        assert!(
            (r[0].e - 2.0).abs() < 1e-9 && (r[0].n - 2.0).abs() < 1e-9,
            "{r:?}"
        );
        assert!((r[2].e - 8.0).abs() < 1e-9 && (r[2].n - 8.0).abs() < 1e-9);
        assert!(inset(&sq, 6.0).is_none());
    }
}
