//! Leg → waypoints: the geometry of every leg and pattern (FLIGHTPLAN §3.2-3.4), computed in a
//! local east/north frame per pattern and converted back with WGS-84 geodesics. Pure functions.
//!
//! One file of ~900 lines on purpose: under 500 are code (one short function per leg kind, all
//! sharing the `Ctx` / `wp` helpers and the local-frame conventions), the rest its tests, kept at
//! the bottom of the file they test; splitting by leg kind would scatter those conventions.

use crate::geo::{self, GeoPoint, LocalFrame, Xy};
use crate::model::*;
pub use crate::polygon::auto_sweep;
use crate::polygon::{inset, left_of, polygon_frame, signed_area};
use crate::vehicle::VehicleParams;
use serde::{Deserialize, Serialize};

/// What a waypoint is for, beyond navigation.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WaypointTag {
    /// Plain navigation.
    #[default]
    Nav,
    /// Take-off (NAV_TAKEOFF).
    Takeoff,
    /// Landing (NAV_LAND).
    Land,
}

/// One waypoint of the stream towards the VAS.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Waypoint {
    /// Latitude, degrees.
    pub lat: f64,
    /// Longitude, degrees.
    pub lon: f64,
    /// Altitude, metres in the plan's reference.
    pub alt: f64,
    /// Speed towards this waypoint, m/s.
    pub speed: f64,
    /// Pass over the point (true) or turn before it (fly-by).
    pub fly_over: bool,
    /// Id of the leg that produced it.
    pub leg: String,
    /// Take-off / land / navigation.
    #[serde(default, skip_serializing_if = "is_nav")]
    pub tag: WaypointTag,
    /// Part of a hold or loop that waits for a command or condition (shown once by `expand`).
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub waits: bool,
    /// The plan's landing sequence begins here (its approach's first waypoint, or the landing
    /// where there is no approach): an autopilot mission marks it with DO_LAND_START.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub land_start: bool,
    /// A hold's fix crossing, where its termination is checked.
    #[serde(skip)]
    pub fix_crossing: bool,
    /// Sequence number in the executive's stream (0 until the executive assigns it).
    #[serde(default)]
    pub seq: u64,
    /// Version of the plan it comes from (0 until the executive assigns it).
    #[serde(default)]
    pub version: u64,
}

fn is_nav(t: &WaypointTag) -> bool {
    *t == WaypointTag::Nav
}

impl Waypoint {
    /// The horizontal position.
    pub fn pos(&self) -> GeoPoint {
        GeoPoint::new(self.lat, self.lon)
    }
}

/// Where the vehicle is (or will be) when a leg starts, and what it inherits.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Origin {
    /// Position.
    pub pos: GeoPoint,
    /// Altitude.
    pub alt: f64,
    /// Speed of the previous waypoint.
    pub speed: f64,
}

/// What a leg's expansion needs besides the leg.
#[derive(Clone, Copy, Debug)]
pub struct Ctx<'a> {
    /// The vehicle.
    pub vehicle: &'a VehicleParams,
    /// The previous waypoint (or present position); `None` before the first.
    pub prev: Option<Origin>,
    /// The plan's default speed, if any.
    pub plan_speed: Option<f64>,
}

impl Ctx<'_> {
    fn speed(&self, own: Option<f64>) -> f64 {
        own.or(self.prev.map(|p| p.speed))
            .or(self.plan_speed)
            .unwrap_or(self.vehicle.default_speed)
    }
    fn alt(&self, own: Option<f64>, fix: Option<f64>) -> f64 {
        own.or(fix).or(self.prev.map(|p| p.alt)).unwrap_or(0.0)
    }
}

fn wp(pos: GeoPoint, alt: f64, speed: f64, fly_over: bool, leg: &str) -> Waypoint {
    Waypoint {
        lat: pos.lat,
        lon: pos.lon,
        alt,
        speed,
        fly_over,
        leg: leg.to_string(),
        tag: WaypointTag::Nav,
        waits: false,
        land_start: false,
        fix_crossing: false,
        seq: 0,
        version: 0,
    }
}

/// Expands a basic leg (IF, TF, DF, CF, RF). DF's "present position" is `ctx.prev`.
pub fn expand_path(leg: &PathLeg, id: &str, ctx: &Ctx<'_>) -> Vec<Waypoint> {
    let alt = ctx.alt(leg.common.alt, leg.fix.alt);
    let speed = ctx.speed(leg.common.speed);
    let fly_over = leg.common.fly_over.unwrap_or(false);
    let end = wp(leg.fix.pos, alt, speed, fly_over, id);
    let out = match leg.kind {
        PathKind::IF => match ctx.prev {
            None => vec![end],
            Some(_) => Vec::new(),
        },
        PathKind::TF | PathKind::DF => vec![end],
        PathKind::CF => {
            let course = leg.course.unwrap_or(0.0);
            let d = leg.length.unwrap_or(ctx.vehicle.cf_length);
            let start = geo::direct(leg.fix.pos, geo::wrap360(course + 180.0), d);
            vec![wp(start, alt, speed, false, id), end]
        }
        PathKind::RF => match (ctx.prev, leg.center) {
            (Some(prev), Some(c)) => {
                let frame = LocalFrame::new(c);
                let (a, b) = (frame.to_local(prev.pos), frame.to_local(leg.fix.pos));
                let sign = leg.turn.unwrap_or(Turn::R).sign();
                let sweep = if sign > 0.0 {
                    geo::wrap360(b.bearing() - a.bearing())
                } else {
                    geo::wrap360(a.bearing() - b.bearing())
                };
                let pts = arc(Xy::default(), a, b, sign, sweep, ctx.vehicle);
                let mut v: Vec<Waypoint> = pts
                    .iter()
                    .map(|p| wp(frame.to_geo(*p), alt, speed, false, id))
                    .collect();
                v.pop();
                v.push(end);
                v
            }
            _ => vec![end],
        },
    };
    out
}

/// Points along an arc around `c` from `a` to `b` turning `sign` (+1 clockwise) through `sweep`
/// degrees, radius interpolated from |a-c| to |b-c|; excludes `a`, ends exactly at `b`. The step
/// is at most the vehicle's arc step and, when the arc allows, at least its minimum waypoint
/// distance.
pub fn arc(c: Xy, a: Xy, b: Xy, sign: f64, sweep: f64, v: &VehicleParams) -> Vec<Xy> {
    let (r0, r1) = (a.minus(c).norm(), b.minus(c).norm());
    let a0 = a.minus(c).bearing();
    let len = sweep.to_radians() * (r0 + r1) / 2.0;
    let mut n = (sweep / v.max_arc_step_deg).ceil().max(1.0) as usize;
    while n > 1 && len / n as f64 + 1e-9 < v.min_wp_distance {
        n -= 1;
    }
    let mut out: Vec<Xy> = (1..n)
        .map(|k| {
            let t = k as f64 / n as f64;
            c.plus(Xy::unit(a0 + sign * sweep * t).scale(r0 + (r1 - r0) * t))
        })
        .collect();
    out.push(b);
    out
}

/// The hold's geometry in its local frame around the fix.
struct HoldGeom {
    frame: LocalFrame,
    u: Xy,
    s: Xy,
    r: f64,
    len: f64,
}

fn hold_geom(h: &Hold, ctx: &Ctx<'_>) -> HoldGeom {
    let theta = h.inbound_course;
    let sigma = h.turn.sign();
    let (st, ct) = theta.to_radians().sin_cos();
    let speed = ctx.speed(h.common.speed);
    HoldGeom {
        frame: LocalFrame::new(h.fix.pos),
        u: Xy::new(st, ct),
        s: Xy::new(ct, -st).scale(sigma),
        r: h.flown_width(ctx.vehicle) / 2.0,
        len: h.length.unwrap_or_else(|| h.time.unwrap_or(60.0) * speed),
    }
}

/// The hold's altitude: HA flies at its target.
pub fn hold_alt(h: &Hold, ctx: &Ctx<'_>) -> f64 {
    match h.kind {
        HoldKind::HA => h
            .target_alt
            .unwrap_or_else(|| ctx.alt(h.common.alt, h.fix.alt)),
        _ => ctx.alt(h.common.alt, h.fix.alt),
    }
}

/// The hold entry: direct to the fix (W0), which is a fix crossing. (Teardrop and parallel
/// entries are not generated: a UAS flies direct entries, FLIGHTPLAN §3.3's "simpler option".)
pub fn hold_entry(h: &Hold, id: &str, ctx: &Ctx<'_>) -> Vec<Waypoint> {
    let mut w0 = wp(
        h.fix.pos,
        hold_alt(h, ctx),
        ctx.speed(h.common.speed),
        h.common.fly_over.unwrap_or(true),
        id,
    );
    w0.fix_crossing = true;
    vec![w0]
}

/// One circuit after the fix: W1..W5 (densified turns) and back to W0 (a fix crossing).
pub fn hold_circuit(h: &Hold, id: &str, ctx: &Ctx<'_>) -> Vec<Waypoint> {
    let g = hold_geom(h, ctx);
    let f = Xy::default();
    let alt = hold_alt(h, ctx);
    let speed = ctx.speed(h.common.speed);
    let sigma = h.turn.sign();
    let w2 = f.plus(g.s.scale(2.0 * g.r));
    let w3 = w2.minus(g.u.scale(g.len));
    let w5 = f.minus(g.u.scale(g.len));
    let mut pts: Vec<(Xy, bool)> = Vec::new();
    match h.shape {
        HoldShape::Racetrack => {
            let c1 = f.plus(g.s.scale(g.r));
            pts.extend(
                arc(c1, f, w2, sigma, 180.0, ctx.vehicle)
                    .into_iter()
                    .map(|p| (p, false)),
            );
            pts.push((w3, false));
            let c2 = w5.plus(g.s.scale(g.r));
            pts.extend(
                arc(c2, w3, w5, sigma, 180.0, ctx.vehicle)
                    .into_iter()
                    .map(|p| (p, false)),
            );
        }
        HoldShape::Rectangle => {
            pts.push((w2, true));
            pts.push((w3, true));
            pts.push((w5, true));
        }
    }
    let mut out: Vec<Waypoint> = pts
        .into_iter()
        .map(|(p, over)| wp(g.frame.to_geo(p), alt, speed, over, id))
        .collect();
    let mut w0 = wp(h.fix.pos, alt, speed, h.common.fly_over.unwrap_or(true), id);
    w0.fix_crossing = true;
    out.push(w0);
    out
}

/// Expands a boustrophedon scan (FLIGHTPLAN §3.4), see [`scan_tracks`].
pub fn expand_scan(s: &Scan, id: &str, ctx: &Ctx<'_>) -> Vec<Waypoint> {
    let frame = polygon_frame(&s.polygon);
    let alt = ctx.alt(s.common.alt, None);
    let speed = ctx.speed(s.common.speed);
    let prev = ctx.prev.map(|p| frame.to_local(p.pos));
    scan_tracks(s, &frame, prev)
        .into_iter()
        .flat_map(|(a, b)| [a, b])
        .map(|p| wp(frame.to_geo(p), alt, speed, true, id))
        .collect()
}

/// Crossings of the line `v = const` (in the rotated frame) with the polygon, paired even/odd.
fn intervals_at(uv: &[(f64, f64)], v: f64) -> Vec<(f64, f64)> {
    let n = uv.len();
    let mut xs = Vec::new();
    for i in 0..n {
        let (a, b) = (uv[i], uv[(i + 1) % n]);
        if (a.1 > v) != (b.1 > v) {
            xs.push(a.0 + (v - a.1) / (b.1 - a.1) * (b.0 - a.0));
        }
    }
    xs.sort_by(f64::total_cmp);
    xs.chunks_exact(2).map(|c| (c[0], c[1])).collect()
}

/// The scan's tracks as (start, end) pairs in flying order, in `frame`.
///
/// Tracks run along the sweep bearing, `spacing` apart and centred on the polygon across the
/// sweep, so each border is at most `spacing/2` from the outer track. Each track covers the
/// band `spacing/2` either side of it: it spans the polygon's extent over the whole band (not
/// just on its centre line), so every point of the polygon lies within `spacing/2` of a track.
///
/// Concave polygons: a band that meets the polygon in several separate pieces gets one track
/// per piece, all flown in the band's direction; between two pieces the vehicle flies straight
/// across the notch (outside the area) with no waypoint in between.
pub fn scan_tracks(s: &Scan, frame: &LocalFrame, prev: Option<Xy>) -> Vec<(Xy, Xy)> {
    let pts: Vec<Xy> = s.polygon.iter().map(|p| frame.to_local(*p)).collect();
    let bearing = s.sweep_angle.map_or_else(|| auto_sweep(&pts), geo::wrap360);
    let d = Xy::unit(bearing);
    let left = left_of(bearing);
    let uv: Vec<(f64, f64)> = pts.iter().map(|p| (p.dot(d), p.dot(left))).collect();
    let (vmin, vmax) = uv
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
            (lo.min(p.1), hi.max(p.1))
        });
    let sp = s.spacing;
    let width = vmax - vmin;
    // A centimetre of slack: projections from nearby origins differ by the meridian convergence
    // (a few micro-radians), which must not add a track.
    let k = ((width - 0.01) / sp).ceil().max(1.0) as usize;
    let mid = (vmin + vmax) / 2.0;
    let eps = 1e-6 * (1.0 + width);
    // Lines from right (low v) to left (high v), each with its pieces sorted by u.
    let mut with_v: Vec<(f64, Vec<(f64, f64)>)> = Vec::new();
    for i in 0..k {
        let vk = mid - (k as f64 - 1.0) * sp / 2.0 + i as f64 * sp;
        let (lo, hi) = (
            (vk - sp / 2.0).max(vmin + eps),
            (vk + sp / 2.0).min(vmax - eps),
        );
        let mut samples: Vec<f64> = (0..=8).map(|j| lo + (hi - lo) * j as f64 / 8.0).collect();
        for p in &uv {
            for dv in [-eps, eps] {
                if p.1 + dv > lo && p.1 + dv < hi {
                    samples.push(p.1 + dv);
                }
            }
        }
        let mut ivs: Vec<(f64, f64)> = samples.iter().flat_map(|v| intervals_at(&uv, *v)).collect();
        ivs.sort_by(|a, b| a.0.total_cmp(&b.0));
        let mut merged: Vec<(f64, f64)> = Vec::new();
        for iv in ivs {
            match merged.last_mut() {
                Some(last) if iv.0 <= last.1 => last.1 = last.1.max(iv.1),
                _ => merged.push(iv),
            }
        }
        if !merged.is_empty() {
            with_v.push((vk, merged));
        }
    }
    let to_xy = |u: f64, v: f64| d.scale(u).plus(left.scale(v));
    let build = |left_first: bool, forward_first: bool| -> Vec<(Xy, Xy)> {
        let mut order: Vec<&(f64, Vec<(f64, f64)>)> = with_v.iter().collect();
        if left_first {
            order.reverse();
        }
        let mut out = Vec::new();
        for (i, (v, pieces)) in order.into_iter().enumerate() {
            let forward = forward_first == (i % 2 == 0);
            let mut segs: Vec<(Xy, Xy)> = pieces
                .iter()
                .map(|(a, b)| {
                    if forward {
                        (to_xy(*a, *v), to_xy(*b, *v))
                    } else {
                        (to_xy(*b, *v), to_xy(*a, *v))
                    }
                })
                .collect();
            if !forward {
                segs.reverse();
            }
            out.extend(segs);
        }
        out
    };
    let lefts: &[bool] = match s.entry {
        ScanEntry::Left => &[true],
        ScanEntry::Right => &[false],
        ScanEntry::Nearest => &[true, false],
    };
    let fwds: &[bool] = match s.start_side {
        ScanStart::Back => &[true],
        ScanStart::Front => &[false],
        ScanStart::Nearest => &[true, false],
    };
    let mut best: Option<(f64, Vec<(Xy, Xy)>)> = None;
    for &l in lefts {
        for &f in fwds {
            let t = build(l, f);
            let dist = match (prev, t.first()) {
                (Some(p), Some(first)) => first.0.minus(p).norm(),
                _ => 0.0,
            };
            if best.as_ref().is_none_or(|b| dist < b.0 - 1e-9) {
                best = Some((dist, t));
            }
        }
    }
    best.map(|b| b.1).unwrap_or_default()
}

/// Expands a perimeter pattern: rings at `spacing/2`, `3·spacing/2`, ... inside the polygon
/// (fewer when the polygon is too small), each starting at its vertex nearest the previous
/// position and closed back to it.
pub fn expand_perimeter(p: &Perimeter, id: &str, ctx: &Ctx<'_>) -> Vec<Waypoint> {
    let frame = polygon_frame(&p.polygon);
    let pts: Vec<Xy> = p.polygon.iter().map(|q| frame.to_local(*q)).collect();
    let alt = ctx.alt(p.common.alt, None);
    let speed = ctx.speed(p.common.speed);
    let mut cur = ctx.prev.map(|o| frame.to_local(o.pos));
    let mut out = Vec::new();
    for k in 0..p.rings {
        let Some(mut ring) = inset(&pts, p.spacing / 2.0 + f64::from(k) * p.spacing) else {
            break;
        };
        // Signed area > 0 is anticlockwise; R flies clockwise.
        if (signed_area(&ring) > 0.0) == (p.turn == Turn::R) {
            ring.reverse();
        }
        let start = cur.map_or(0, |c| {
            (0..ring.len())
                .min_by(|a, b| {
                    ring[*a]
                        .minus(c)
                        .norm()
                        .total_cmp(&ring[*b].minus(c).norm())
                })
                .unwrap_or(0)
        });
        for i in 0..=ring.len() {
            let q = ring[(start + i) % ring.len()];
            out.push(wp(frame.to_geo(q), alt, speed, false, id));
        }
        cur = Some(ring[start]);
    }
    out
}

/// Take-off: one waypoint above the fix at its clearance altitude.
pub fn expand_takeoff(t: &Takeoff, id: &str, ctx: &Ctx<'_>) -> Vec<Waypoint> {
    let mut w = wp(
        t.fix.pos,
        t.fix.alt.unwrap_or(0.0) + t.clear_alt,
        ctx.speed(None),
        true,
        id,
    );
    w.tag = WaypointTag::Takeoff;
    vec![w]
}

/// Landing: one waypoint at the touchdown fix.
pub fn expand_landing(l: &Landing, id: &str, ctx: &Ctx<'_>) -> Vec<Waypoint> {
    let mut w = wp(
        l.fix.pos,
        l.fix.alt.unwrap_or(0.0),
        ctx.speed(None),
        true,
        id,
    );
    w.tag = WaypointTag::Land;
    vec![w]
}

/// Drops waypoints closer than the vehicle's minimum distance to the one before (003 §6.2.3).
/// Take-off and landing points are always kept.
pub fn enforce_min_distance(prev: Option<GeoPoint>, wps: Vec<Waypoint>, min: f64) -> Vec<Waypoint> {
    let mut last = prev;
    let mut out = Vec::with_capacity(wps.len());
    for w in wps {
        let keep =
            w.tag != WaypointTag::Nav || last.is_none_or(|l| geo::distance(l, w.pos()) >= min);
        if keep {
            last = Some(w.pos());
            out.push(w);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::parse::parse_plan;

    fn fix(lat: f64, lon: f64) -> Fix {
        Fix {
            id: "F".into(),
            pos: GeoPoint::new(lat, lon),
            alt: Some(100.0),
        }
    }

    fn test_vehicle() -> VehicleParams {
        VehicleParams {
            max_arc_step_deg: 90.0,
            min_wp_distance: 1.0,
            ..VehicleParams::aircraft()
        }
    }

    fn hold(turn: Turn, course: f64) -> Hold {
        Hold {
            kind: HoldKind::HF,
            fix: fix(41.29, 1.96),
            inbound_course: course,
            turn,
            length: Some(600.0),
            time: None,
            width: Some(250.0),
            shape: HoldShape::Racetrack,
            circuits: None,
            until: None,
            target_alt: None,
            alt_tolerance: 5.0,
            common: LegCommon::default(),
        }
    }

    fn local(frame: &LocalFrame, w: &Waypoint) -> Xy {
        frame.to_local(w.pos())
    }

    fn close(a: Xy, e: f64, n: f64) -> bool {
        (a.e - e).abs() < 0.01 && (a.n - n).abs() < 0.01
    }

    #[test]
    fn golden_hold_right_and_left() {
        let v = test_vehicle();
        let ctx = Ctx {
            vehicle: &v,
            prev: None,
            plan_speed: Some(20.0),
        };
        // Inbound course 90 (flying east to the fix). Right turns hold on the south side.
        let h = hold(Turn::R, 90.0);
        let c = hold_circuit(&h, "h", &ctx);
        let f = LocalFrame::new(h.fix.pos);
        let got: Vec<Xy> = c.iter().map(|w| local(&f, w)).collect();
        let want = [
            (125.0, -125.0),
            (0.0, -250.0),
            (-600.0, -250.0),
            (-725.0, -125.0),
            (-600.0, 0.0),
            (0.0, 0.0),
        ];
        assert_eq!(got.len(), want.len(), "{got:?}");
        for (g, w) in got.iter().zip(want) {
            assert!(close(*g, w.0, w.1), "{g:?} vs {w:?}");
        }
        assert!(c.last().unwrap().fix_crossing && c.last().unwrap().fly_over);
        assert!(c
            .iter()
            .all(|w| w.alt == 100.0 && w.speed == 20.0 && w.leg == "h"));
        // Left turns mirror to the north side.
        let h = hold(Turn::L, 90.0);
        let got: Vec<Xy> = hold_circuit(&h, "h", &ctx)
            .iter()
            .map(|w| local(&f, w))
            .collect();
        let want = [
            (125.0, 125.0),
            (0.0, 250.0),
            (-600.0, 250.0),
            (-725.0, 125.0),
            (-600.0, 0.0),
            (0.0, 0.0),
        ];
        for (g, w) in got.iter().zip(want) {
            assert!(close(*g, w.0, w.1), "{g:?} vs {w:?}");
        }
    }

    #[test]
    fn golden_rectangle_hold_for_a_rover() {
        let v = VehicleParams::rover();
        let ctx = Ctx {
            vehicle: &v,
            prev: None,
            plan_speed: None,
        };
        let mut h = hold(Turn::R, 0.0);
        h.shape = HoldShape::Rectangle;
        h.length = Some(30.0);
        h.width = Some(12.0);
        let f = LocalFrame::new(h.fix.pos);
        let c = hold_circuit(&h, "h", &ctx);
        let got: Vec<Xy> = c.iter().map(|w| local(&f, w)).collect();
        let want = [(12.0, 0.0), (12.0, -30.0), (0.0, -30.0), (0.0, 0.0)];
        assert_eq!(got.len(), 4);
        for (g, w) in got.iter().zip(want) {
            assert!(close(*g, w.0, w.1), "{g:?} vs {w:?}");
        }
        assert!(c.iter().all(|w| w.fly_over));
    }

    #[test]
    fn golden_basic_legs() {
        let v = test_vehicle();
        let f = fix(41.0, 2.0);
        let leg = |kind| PathLeg {
            kind,
            fix: f.clone(),
            course: Some(90.0),
            length: Some(1000.0),
            center: None,
            turn: None,
            common: LegCommon::default(),
        };
        let none = Ctx {
            vehicle: &v,
            prev: None,
            plan_speed: None,
        };
        let prev = Origin {
            pos: GeoPoint::new(41.01, 2.0),
            alt: 50.0,
            speed: 15.0,
        };
        let some = Ctx {
            prev: Some(prev),
            ..none
        };
        assert_eq!(expand_path(&leg(PathKind::IF), "a", &none).len(), 1);
        assert!(expand_path(&leg(PathKind::IF), "a", &some).is_empty());
        for k in [PathKind::TF, PathKind::DF] {
            let w = expand_path(&leg(k), "a", &some);
            assert_eq!(w.len(), 1);
            assert_eq!(
                (w[0].lat, w[0].lon, w[0].alt, w[0].speed, w[0].fly_over),
                (41.0, 2.0, 100.0, 15.0, false)
            );
        }
        let w = expand_path(&leg(PathKind::CF), "a", &some);
        assert_eq!(w.len(), 2);
        let lf = LocalFrame::new(f.pos);
        assert!(
            close(local(&lf, &w[0]), -1000.0, 0.0),
            "{:?}",
            local(&lf, &w[0])
        );
        // RF: quarter circle from north of the centre to east of it, turning right.
        let c = GeoPoint::new(41.0, 2.0);
        let cf = LocalFrame::new(c);
        let start = cf.to_geo(Xy::new(0.0, 500.0));
        let end = cf.to_geo(Xy::new(500.0, 0.0));
        let mut rf = leg(PathKind::RF);
        rf.fix.pos = end;
        rf.center = Some(c);
        rf.turn = Some(Turn::R);
        let ctx = Ctx {
            prev: Some(Origin { pos: start, ..prev }),
            vehicle: &VehicleParams {
                max_arc_step_deg: 30.0,
                ..test_vehicle()
            },
            plan_speed: None,
        };
        let w = expand_path(&rf, "a", &ctx);
        assert_eq!(w.len(), 3);
        let p = local(&cf, &w[0]);
        assert!(close(p, 250.0, 433.0127), "{p:?}");
        assert!(close(local(&cf, &w[2]), 500.0, 0.0));
        for x in &w {
            assert!((local(&cf, x).norm() - 500.0).abs() < 0.01);
        }
    }

    fn square_scan(entry: ScanEntry, start: ScanStart, sweep: Option<f64>) -> Scan {
        let f = LocalFrame::new(GeoPoint::new(41.275, 1.987));
        let poly = [(-50.0, -30.0), (50.0, -30.0), (50.0, 30.0), (-50.0, 30.0)]
            .iter()
            .map(|(e, n)| f.to_geo(Xy::new(*e, *n)))
            .collect();
        Scan {
            polygon: poly,
            spacing: 10.0,
            sweep_angle: sweep,
            entry,
            start_side: start,
            common: LegCommon::default(),
        }
    }

    #[test]
    fn golden_scan_entry_and_side_variants() {
        let v = VehicleParams::rover();
        let ctx = Ctx {
            vehicle: &v,
            prev: None,
            plan_speed: None,
        };
        // Tracks east (sweep 90): left is north. 60 m wide / 10 m = 6 tracks at n = 25, 15, ... -25.
        let s = square_scan(ScanEntry::Left, ScanStart::Back, Some(90.0));
        let frame = polygon_frame(&s.polygon);
        let w = expand_scan(&s, "s", &ctx);
        assert_eq!(w.len(), 12);
        let first = local(&frame, &w[0]);
        assert!(close(first, -50.0, 25.0), "{first:?}");
        assert!(close(local(&frame, &w[1]), 50.0, 25.0));
        assert!(close(local(&frame, &w[2]), 50.0, 15.0));
        assert!(close(local(&frame, &w[11]), -50.0, -25.0));
        assert!(w.iter().all(|x| x.fly_over));
        let first_of = |e, st| {
            let s = square_scan(e, st, Some(90.0));
            local(&frame, &expand_scan(&s, "s", &ctx)[0])
        };
        assert!(close(
            first_of(ScanEntry::Right, ScanStart::Back),
            -50.0,
            -25.0
        ));
        assert!(close(
            first_of(ScanEntry::Left, ScanStart::Front),
            50.0,
            25.0
        ));
        assert!(close(
            first_of(ScanEntry::Right, ScanStart::Front),
            50.0,
            -25.0
        ));
        // Nearest: from a point near the south-east corner.
        let near = Ctx {
            prev: Some(Origin {
                pos: frame.to_geo(Xy::new(70.0, -40.0)),
                alt: 0.0,
                speed: 1.0,
            }),
            ..ctx
        };
        let s = square_scan(ScanEntry::Nearest, ScanStart::Nearest, Some(90.0));
        assert!(close(
            local(&frame, &expand_scan(&s, "s", &near)[0]),
            50.0,
            -25.0
        ));
    }

    #[test]
    fn auto_sweep_picks_fewest_tracks() {
        let s = square_scan(ScanEntry::Left, ScanStart::Back, None);
        let w = expand_scan(
            &s,
            "s",
            &Ctx {
                vehicle: &VehicleParams::rover(),
                prev: None,
                plan_speed: None,
            },
        );
        // 100 m × 60 m: tracks along the long side → 6 tracks, 12 points.
        assert_eq!(w.len(), 12);
    }

    fn seg_dist(p: Xy, a: Xy, b: Xy) -> f64 {
        let ab = b.minus(a);
        let t = if ab.norm() < 1e-12 {
            0.0
        } else {
            (p.minus(a).dot(ab) / ab.dot(ab)).clamp(0.0, 1.0)
        };
        p.minus(a.plus(ab.scale(t))).norm()
    }

    fn assert_covered(s: &Scan) {
        let frame = polygon_frame(&s.polygon);
        let tracks = scan_tracks(s, &frame, None);
        let pts: Vec<Xy> = s.polygon.iter().map(|p| frame.to_local(*p)).collect();
        let (mut lo, mut hi) = (Xy::new(f64::MAX, f64::MAX), Xy::new(f64::MIN, f64::MIN));
        for p in &pts {
            lo = Xy::new(lo.e.min(p.e), lo.n.min(p.n));
            hi = Xy::new(hi.e.max(p.e), hi.n.max(p.n));
        }
        let mut checked = 0;
        for i in 0..=60 {
            for j in 0..=60 {
                let p = Xy::new(
                    lo.e + (hi.e - lo.e) * i as f64 / 60.0,
                    lo.n + (hi.n - lo.n) * j as f64 / 60.0,
                );
                if !crate::polygon::contains(&pts, p) {
                    continue;
                }
                checked += 1;
                let d = tracks
                    .iter()
                    .map(|(a, b)| seg_dist(p, *a, *b))
                    .fold(f64::MAX, f64::min);
                assert!(
                    d <= s.spacing / 2.0 + 0.02,
                    "point {p:?} is {d} m from the nearest track"
                );
            }
        }
        assert!(checked > 500);
        // The polygon's vertices too.
        for p in &pts {
            let d = tracks
                .iter()
                .map(|(a, b)| seg_dist(*p, *a, *b))
                .fold(f64::MAX, f64::min);
            assert!(d <= s.spacing / 2.0 + 0.02, "vertex {p:?} is {d} m away");
        }
    }

    #[test]
    fn scan_covers_convex_polygons_within_half_spacing() {
        for sweep in [None, Some(0.0), Some(33.0), Some(90.0), Some(151.0)] {
            let mut s = square_scan(ScanEntry::Left, ScanStart::Back, sweep);
            assert_covered(&s);
            // A skewed quadrilateral (the FLIGHTPLAN example's area).
            s.polygon = vec![
                GeoPoint::new(41.3010, 1.9550),
                GeoPoint::new(41.3060, 1.9650),
                GeoPoint::new(41.3020, 1.9750),
                GeoPoint::new(41.2970, 1.9640),
            ];
            s.spacing = 120.0;
            assert_covered(&s);
        }
    }

    #[test]
    fn concave_polygon_gets_one_track_per_piece() {
        // A U open to the north: 60 m wide, arms 20 m wide, notch 20 m wide and 35 m deep.
        let f = LocalFrame::new(GeoPoint::new(41.275, 1.987));
        let poly: Vec<GeoPoint> = [
            (0.0, 0.0),
            (60.0, 0.0),
            (60.0, 60.0),
            (40.0, 60.0),
            (40.0, 25.0),
            (20.0, 25.0),
            (20.0, 60.0),
            (0.0, 60.0),
        ]
        .iter()
        .map(|(e, n)| f.to_geo(Xy::new(*e, *n)))
        .collect();
        let s = Scan {
            polygon: poly,
            spacing: 10.0,
            sweep_angle: Some(90.0),
            entry: ScanEntry::Left,
            start_side: ScanStart::Back,
            common: LegCommon::default(),
        };
        assert_covered(&s);
        let frame = polygon_frame(&s.polygon);
        let tracks = scan_tracks(&s, &frame, None);
        // 6 bands; the 3 northern ones meet both arms (2 pieces each); the others meet the base
        // (the third band holds the notch's end, so its pieces join into one).
        assert_eq!(tracks.len(), 3 * 2 + 3);
        // The first band is flown eastwards: west arm then east arm, same direction.
        assert!(tracks[0].0.e < tracks[0].1.e && tracks[1].0.e < tracks[1].1.e);
        assert!(tracks[0].1.e < tracks[1].0.e);
    }

    #[test]
    fn perimeter_rings_inside() {
        let s = square_scan(ScanEntry::Left, ScanStart::Back, None);
        let p = Perimeter {
            polygon: s.polygon.clone(),
            spacing: 10.0,
            rings: 10,
            turn: Turn::R,
            common: LegCommon::default(),
        };
        let v = VehicleParams::rover();
        let w = expand_perimeter(
            &p,
            "p",
            &Ctx {
                vehicle: &v,
                prev: None,
                plan_speed: None,
            },
        );
        // 60 m across: rings at 5, 15, 25 m inside; the fourth would collapse.
        assert_eq!(w.len(), 3 * 5);
        let frame = polygon_frame(&p.polygon);
        let a = local(&frame, &w[0]);
        assert!(close(a, -45.0, 25.0), "{a:?}");
        // Clockwise: from the NW corner the next is the NE corner.
        assert!(close(local(&frame, &w[1]), 45.0, 25.0));
        assert!(close(local(&frame, &w[4]), -45.0, 25.0));
        assert!(close(local(&frame, &w[5]), -35.0, 15.0));
    }

    #[test]
    fn min_distance_drops_close_points() {
        let v = VehicleParams::rover();
        let a = wp(GeoPoint::new(41.0, 2.0), 0.0, 1.0, false, "x");
        let b = wp(geo::direct(a.pos(), 0.0, 3.0), 0.0, 1.0, false, "x");
        let c = wp(geo::direct(a.pos(), 0.0, 8.0), 0.0, 1.0, false, "x");
        let out = enforce_min_distance(None, vec![a, b, c], v.min_wp_distance);
        assert_eq!(out.len(), 2);
    }

    #[test]
    fn parsed_scan_round_trip() {
        let src = r#"<flightPlan><mission><scan spacing="10" sweepAngle="0"><pt lat="41.2750" lon="1.9870"/><pt lat="41.2760" lon="1.9870"/><pt lat="41.2760" lon="1.9882"/></scan></mission></flightPlan>"#;
        let p = parse_plan(src).unwrap();
        let NodeKind::Scan(s) = &p.mission[0].kind else {
            panic!()
        };
        assert_covered(s);
    }
}
