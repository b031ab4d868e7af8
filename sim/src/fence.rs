//! The geofence of the simulated autopilot, as each family keeps it.
//!
//! Both families take the area as a fence transfer (`mission_type` FENCE, the mission protocol's
//! MISSION_COUNT → MISSION_REQUEST_INT → MISSION_ITEM_INT → MISSION_ACK) of
//! MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION items (one inclusion polygon, in order) and
//! MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION items (an inclusion circle: param1 its radius in metres,
//! x/y its centre's lat/lon ×1e7; one is kept, the last of the transfer). The vehicle must be
//! inside both the polygon (when it has three vertices or more) and the circle.
//!
//! ArduPilot (and the generic and resetting profiles): the circle around home and the ceiling
//! are parameters (`FENCE_RADIUS`, `FENCE_ALT_MAX`), which parts are enforced is `FENCE_TYPE`
//! (bits: 1 ceiling, 2 the `FENCE_RADIUS` circle, 4 the transfer's polygon and circle), the
//! breach action is `FENCE_ACTION` (rover: 0 report, 1 RTL, 2 hold) and the whole is on with
//! `FENCE_ENABLE`.
//!
//! PX4: no `FENCE_*` and no switch; the transfer's area, `GF_MAX_HOR_DIST` (metres from home)
//! and `GF_MAX_VER_DIST` (metres above home; 0 turns either off) are in force unless
//! `GF_ACTION` is 0 (1 warning, 2 hold, 3 return, 4 terminate, 5 land).
//!
//! [`FenceStore`] is the receiving side of that transfer (requests each item, acknowledges
//! the whole; a new count restarts it, a count of 0 or MISSION_CLEAR_ALL clears the fence) and
//! [`FenceStore::breach`] the pure check the simulation step runs: one breach is reported per
//! excursion, again only after the vehicle came back inside. A transfer is refused with
//! MISSION_ACK NO_SPACE when its count is above the store's capacity (`--fence-capacity`,
//! [`DEFAULT_CAPACITY`] items), UNSUPPORTED at an item of another kind (exclusion zones, return
//! point), INVALID_PARAM1 at a circle whose radius is not a positive number, and DENIED for an
//! item with no transfer under way; a refused transfer leaves the fence on board as it was.

use mavlink::dialects::ardupilotmega::{
    MavCmd, MavMessage, MavMissionResult, MavMissionType, MISSION_ACK_DATA,
    MISSION_REQUEST_INT_DATA,
};

use crate::kinematics::{GeoPoint, LocalFrame, Ned};
use crate::mission::Item;

const FENCE: MavMissionType = MavMissionType::MAV_MISSION_TYPE_FENCE;

/// Most items one fence transfer may have unless told otherwise (ArduPilot keeps a few hundred).
pub const DEFAULT_CAPACITY: u16 = 500;

/// The fence parameters as the step reads them.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct FenceParams {
    /// `FENCE_ENABLE` ≥ 1.
    pub enabled: bool,
    /// `FENCE_TYPE` bits.
    pub kinds: u8,
    /// `FENCE_RADIUS`, metres.
    pub radius_m: f64,
    /// `FENCE_ALT_MAX`, metres above home.
    pub alt_max_m: f64,
}

/// A transfer in progress.
#[derive(Debug)]
struct Pending {
    from: (u8, u8),
    count: u16,
    items: Vec<Item>,
}

/// The fence on board and the transfer that may be replacing it.
#[derive(Debug)]
pub struct FenceStore {
    /// Inclusion polygon, local metres (north, east) from home.
    polygon: Vec<(f64, f64)>,
    /// Inclusion circle: its centre, local metres (north, east) from home, and its radius.
    circle: Option<((f64, f64), f64)>,
    pending: Option<Pending>,
    /// Outside now (a breach was reported and the vehicle has not come back).
    breached: bool,
    /// Most items one transfer may have.
    capacity: u16,
}

impl Default for FenceStore {
    fn default() -> Self {
        Self::with_capacity(DEFAULT_CAPACITY)
    }
}

fn ack(to: (u8, u8), result: MavMissionResult) -> MavMessage {
    MavMessage::MISSION_ACK(MISSION_ACK_DATA {
        target_system: to.0,
        target_component: to.1,
        mavtype: result,
        mission_type: FENCE,
        ..Default::default()
    })
}

fn request(to: (u8, u8), seq: u16) -> MavMessage {
    MavMessage::MISSION_REQUEST_INT(MISSION_REQUEST_INT_DATA {
        target_system: to.0,
        target_component: to.1,
        seq,
        mission_type: FENCE,
    })
}

impl FenceStore {
    /// An empty store taking transfers of at most `capacity` items.
    pub fn with_capacity(capacity: u16) -> Self {
        Self {
            polygon: Vec::new(),
            circle: None,
            pending: None,
            breached: false,
            capacity,
        }
    }

    /// Most items one transfer may have (a larger MISSION_COUNT is answered NO_SPACE).
    pub fn capacity(&self) -> u16 {
        self.capacity
    }

    /// Changes the capacity; the fence on board stays.
    pub fn set_capacity(&mut self, capacity: u16) {
        self.capacity = capacity;
    }

    /// Vertices of the polygon on board.
    pub fn vertices(&self) -> usize {
        self.polygon.len()
    }

    /// The radius of the inclusion circle on board, metres.
    pub fn circle_m(&self) -> Option<f64> {
        self.circle.map(|(_, r)| r)
    }

    /// Whether an area (polygon or circle) is on board.
    pub fn has_area(&self) -> bool {
        self.polygon.len() >= 3 || self.circle.is_some()
    }

    /// MISSION_COUNT for the fence: starts a transfer (0 clears; above the capacity: NO_SPACE).
    pub fn on_count(&mut self, from: (u8, u8), count: u16) -> Vec<MavMessage> {
        if count == 0 {
            self.polygon.clear();
            self.circle = None;
            self.pending = None;
            return vec![ack(from, MavMissionResult::MAV_MISSION_ACCEPTED)];
        }
        if count > self.capacity {
            return vec![ack(from, MavMissionResult::MAV_MISSION_NO_SPACE)];
        }
        self.pending = Some(Pending {
            from,
            count,
            items: Vec::new(),
        });
        vec![request(from, 0)]
    }

    /// A fence item. Returns the replies and, when the transfer completed, the new
    /// polygon's vertex count (the circle is [`Self::circle_m`]).
    pub fn on_item(
        &mut self,
        from: (u8, u8),
        item: Item,
        frame: &LocalFrame,
    ) -> (Vec<MavMessage>, Option<usize>) {
        let Some(p) = self.pending.as_mut().filter(|p| p.from == from) else {
            return (vec![ack(from, MavMissionResult::MAV_MISSION_DENIED)], None);
        };
        let expected = p.items.len() as u16;
        if item.seq != expected {
            // A stale resend: ask again for the one we want.
            return (vec![request(from, expected)], None);
        }
        if !matches!(
            item.command,
            MavCmd::MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION
                | MavCmd::MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION
        ) {
            self.pending = None;
            return (
                vec![ack(from, MavMissionResult::MAV_MISSION_UNSUPPORTED)],
                None,
            );
        }
        if item.command == MavCmd::MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION
            && !(item.param1.is_finite() && item.param1 > 0.0)
        {
            self.pending = None;
            return (
                vec![ack(from, MavMissionResult::MAV_MISSION_INVALID_PARAM1)],
                None,
            );
        }
        p.items.push(item);
        if p.items.len() < usize::from(p.count) {
            return (vec![request(from, expected + 1)], None);
        }
        let done = self.pending.take().map(|p| p.items).unwrap_or_default();
        let local = |i: &Item| {
            let n = frame.to_local(GeoPoint {
                lat_deg: f64::from(i.x) / 1e7,
                lon_deg: f64::from(i.y) / 1e7,
                alt_m: frame.home().alt_m,
            });
            (n.north, n.east)
        };
        let is_circle = |i: &&Item| i.command == MavCmd::MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION;
        self.polygon = done.iter().filter(|i| !is_circle(i)).map(local).collect();
        self.circle = done
            .iter()
            .rev()
            .find(is_circle)
            .map(|i| (local(i), f64::from(i.param1)));
        self.breached = false;
        (
            vec![ack(from, MavMissionResult::MAV_MISSION_ACCEPTED)],
            Some(self.polygon.len()),
        )
    }

    /// MISSION_CLEAR_ALL for the fence.
    pub fn on_clear(&mut self, from: (u8, u8)) -> Vec<MavMessage> {
        self.polygon.clear();
        self.circle = None;
        self.pending = None;
        self.breached = false;
        vec![ack(from, MavMissionResult::MAV_MISSION_ACCEPTED)]
    }

    /// The ground station cancelled the transfer.
    pub fn on_ack(&mut self) {
        self.pending = None;
    }

    /// Checks `pos` (local, from home): `Some(reason)` when it has just left the fence.
    pub fn breach(&mut self, p: &FenceParams, pos: &Ned) -> Option<String> {
        let why = if p.enabled {
            self.outside(p, pos)
        } else {
            None
        };
        match (why, self.breached) {
            (Some(why), false) => {
                self.breached = true;
                Some(why)
            }
            (None, _) => {
                self.breached = false;
                None
            }
            _ => None,
        }
    }

    fn outside(&self, p: &FenceParams, pos: &Ned) -> Option<String> {
        let d = pos.north.hypot(pos.east);
        if p.kinds & 2 != 0 && p.radius_m > 0.0 && d > p.radius_m {
            return Some(format!(
                "circle ({d:.0} m from home, radius {:.0} m)",
                p.radius_m
            ));
        }
        if p.kinds & 1 != 0 && p.alt_max_m > 0.0 && pos.up > p.alt_max_m {
            return Some(format!(
                "ceiling ({:.0} m, max {:.0} m)",
                pos.up, p.alt_max_m
            ));
        }
        if p.kinds & 4 != 0 && self.polygon.len() >= 3 && !self.inside(pos) {
            return Some("polygon".into());
        }
        if let (true, Some(((n, e), r))) = (p.kinds & 4 != 0, self.circle) {
            let d = (pos.north - n).hypot(pos.east - e);
            if d > r {
                return Some(format!(
                    "circle item ({d:.0} m from its centre, radius {r:.0} m)"
                ));
            }
        }
        None
    }

    fn inside(&self, pos: &Ned) -> bool {
        let (y, x) = (pos.north, pos.east);
        let poly = &self.polygon;
        let mut inside = false;
        let mut j = poly.len() - 1;
        for i in 0..poly.len() {
            let (yi, xi) = poly[i];
            let (yj, xj) = poly[j];
            if (yi > y) != (yj > y) && x < (xj - xi) * (y - yi) / (yj - yi) + xi {
                inside = !inside;
            }
            j = i;
        }
        inside
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const GCS: (u8, u8) = (255, 190);

    fn frame() -> LocalFrame {
        LocalFrame::new(GeoPoint {
            lat_deg: 41.275,
            lon_deg: 1.987,
            alt_m: 584.0,
        })
    }

    fn vertex(f: &LocalFrame, seq: u16, north: f64, east: f64) -> Item {
        let g = f.to_geo(Ned {
            north,
            east,
            up: 0.0,
        });
        Item {
            seq,
            command: MavCmd::MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION,
            param1: 4.0,
            x: (g.lat_deg * 1e7).round() as i32,
            y: (g.lon_deg * 1e7).round() as i32,
            mission_type: FENCE,
            ..Default::default()
        }
    }

    #[test]
    fn a_polygon_is_received_and_breaches_are_reported_once_per_excursion() {
        let f = frame();
        let mut s = FenceStore::default();
        let out = s.on_count(GCS, 4);
        assert!(
            matches!(out.as_slice(), [MavMessage::MISSION_REQUEST_INT(r)] if r.seq == 0 && r.mission_type == FENCE)
        );
        let corners = [(-50.0, -50.0), (-50.0, 50.0), (50.0, 50.0), (50.0, -50.0)];
        for (i, (n, e)) in corners.iter().enumerate() {
            // A stale resend is answered with the request for the wanted item.
            if i == 2 {
                let (out, _) = s.on_item(GCS, vertex(&f, 0, -50.0, -50.0), &f);
                assert!(
                    matches!(out.as_slice(), [MavMessage::MISSION_REQUEST_INT(r)] if r.seq == 2)
                );
            }
            let (out, done) = s.on_item(GCS, vertex(&f, i as u16, *n, *e), &f);
            if i == 3 {
                assert_eq!(done, Some(4));
                assert!(matches!(out.as_slice(), [MavMessage::MISSION_ACK(a)]
                    if a.mavtype == MavMissionResult::MAV_MISSION_ACCEPTED && a.mission_type == FENCE));
            }
        }
        let p = FenceParams {
            enabled: true,
            kinds: 4 | 1,
            radius_m: 0.0,
            alt_max_m: 30.0,
        };
        let at = |north, east, up| Ned { north, east, up };
        assert_eq!(s.breach(&p, &at(10.0, 10.0, 0.0)), None);
        assert_eq!(
            s.breach(&p, &at(60.0, 0.0, 0.0)).as_deref(),
            Some("polygon")
        );
        assert_eq!(
            s.breach(&p, &at(70.0, 0.0, 0.0)),
            None,
            "once per excursion"
        );
        assert_eq!(s.breach(&p, &at(0.0, 0.0, 0.0)), None);
        assert!(s
            .breach(&p, &at(0.0, 0.0, 31.0))
            .unwrap()
            .starts_with("ceiling"));
        let off = FenceParams {
            enabled: false,
            ..p
        };
        assert_eq!(s.breach(&off, &at(100.0, 0.0, 0.0)), None);
        let circle = FenceParams {
            enabled: true,
            kinds: 2,
            radius_m: 80.0,
            alt_max_m: 0.0,
        };
        assert!(s
            .breach(&circle, &at(100.0, 0.0, 0.0))
            .unwrap()
            .starts_with("circle (100 m"));
        assert!(s.on_clear(GCS).len() == 1 && s.vertices() == 0);
    }

    #[test]
    fn a_circle_item_is_kept_beside_the_polygon_and_enforced() {
        let f = frame();
        let mut s = FenceStore::default();
        s.on_count(GCS, 2);
        let mut circle = vertex(&f, 1, 20.0, 0.0);
        circle.command = MavCmd::MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION;
        circle.param1 = 50.0;
        s.on_item(GCS, vertex(&f, 0, 0.0, 0.0), &f);
        let (out, done) = s.on_item(GCS, circle, &f);
        assert!(matches!(out.as_slice(), [MavMessage::MISSION_ACK(a)]
            if a.mavtype == MavMissionResult::MAV_MISSION_ACCEPTED));
        assert_eq!((done, s.circle_m()), (Some(1), Some(50.0)));
        assert!(s.has_area());
        let p = FenceParams {
            enabled: true,
            kinds: 4,
            radius_m: 0.0,
            alt_max_m: 0.0,
        };
        let at = |north, east| Ned {
            north,
            east,
            up: 0.0,
        };
        assert_eq!(
            s.breach(&p, &at(60.0, 0.0)),
            None,
            "within 50 m of its centre"
        );
        let why = s.breach(&p, &at(-40.0, 0.0)).expect("a breach");
        assert!(
            why.starts_with("circle item (60 m from its centre"),
            "{why}"
        );
        s.on_clear(GCS);
        assert!(!s.has_area() && s.circle_m().is_none());
    }

    #[test]
    fn odd_transfers_are_refused() {
        let f = frame();
        let mut s = FenceStore::default();
        assert!(matches!(s.on_count(GCS, DEFAULT_CAPACITY + 1).as_slice(),
            [MavMessage::MISSION_ACK(a)] if a.mavtype == MavMissionResult::MAV_MISSION_NO_SPACE));
        // An item with no transfer.
        let (out, _) = s.on_item(GCS, vertex(&f, 0, 0.0, 0.0), &f);
        assert!(
            matches!(out.as_slice(), [MavMessage::MISSION_ACK(a)] if a.mavtype == MavMissionResult::MAV_MISSION_DENIED)
        );
        // Not an inclusion area (an exclusion circle).
        s.on_count(GCS, 1);
        let mut item = vertex(&f, 0, 0.0, 0.0);
        item.command = MavCmd::MAV_CMD_NAV_FENCE_CIRCLE_EXCLUSION;
        let (out, _) = s.on_item(GCS, item, &f);
        assert!(
            matches!(out.as_slice(), [MavMessage::MISSION_ACK(a)] if a.mavtype == MavMissionResult::MAV_MISSION_UNSUPPORTED)
        );
    }

    fn circle(f: &LocalFrame, seq: u16, north: f64, east: f64, radius: f32) -> Item {
        Item {
            command: MavCmd::MAV_CMD_NAV_FENCE_CIRCLE_INCLUSION,
            param1: radius,
            ..vertex(f, seq, north, east)
        }
    }

    /// Sends `items` as one transfer; returns the last replies and the completion.
    fn transfer(
        s: &mut FenceStore,
        f: &LocalFrame,
        items: &[Item],
    ) -> (Vec<MavMessage>, Option<usize>) {
        let out = s.on_count(GCS, items.len() as u16);
        assert!(
            matches!(out.as_slice(), [MavMessage::MISSION_REQUEST_INT(r)] if r.seq == 0),
            "{out:?}"
        );
        let mut last = (Vec::new(), None);
        for item in items {
            last = s.on_item(GCS, item.clone(), f);
        }
        last
    }

    fn acked(out: &[MavMessage]) -> Option<MavMissionResult> {
        match out {
            [MavMessage::MISSION_ACK(a)] if a.mission_type == FENCE => Some(a.mavtype),
            _ => None,
        }
    }

    #[test]
    fn the_capacity_bounds_one_transfer_and_a_refusal_keeps_the_fence() {
        let f = frame();
        assert_eq!(FenceStore::default().capacity(), 500);
        let mut s = FenceStore::with_capacity(4);
        // Four items fit: three vertices and a circle.
        let items = [
            vertex(&f, 0, -50.0, -50.0),
            vertex(&f, 1, -50.0, 50.0),
            vertex(&f, 2, 50.0, 0.0),
            circle(&f, 3, 0.0, 0.0, 40.0),
        ];
        let (out, done) = transfer(&mut s, &f, &items);
        assert_eq!(acked(&out), Some(MavMissionResult::MAV_MISSION_ACCEPTED));
        assert_eq!((done, s.circle_m()), (Some(3), Some(40.0)));
        // Five do not: NO_SPACE at the count, and the fence on board stays.
        assert_eq!(
            acked(&s.on_count(GCS, 5)),
            Some(MavMissionResult::MAV_MISSION_NO_SPACE)
        );
        assert_eq!((s.vertices(), s.circle_m()), (3, Some(40.0)));
        // A larger capacity takes them.
        s.set_capacity(5);
        assert!(matches!(s.on_count(GCS, 5).as_slice(),
            [MavMessage::MISSION_REQUEST_INT(r)] if r.seq == 0));
        // No capacity at all still lets a ground station clear the fence.
        let mut none = FenceStore::with_capacity(0);
        assert_eq!(
            acked(&none.on_count(GCS, 1)),
            Some(MavMissionResult::MAV_MISSION_NO_SPACE)
        );
        assert_eq!(
            acked(&none.on_count(GCS, 0)),
            Some(MavMissionResult::MAV_MISSION_ACCEPTED)
        );
    }

    #[test]
    fn a_later_circle_replaces_an_earlier_one_and_a_bad_radius_is_refused() {
        let f = frame();
        let mut s = FenceStore::default();
        let (out, done) = transfer(
            &mut s,
            &f,
            &[
                circle(&f, 0, 0.0, 0.0, 10.0),
                circle(&f, 1, 100.0, 0.0, 30.0),
            ],
        );
        assert_eq!(acked(&out), Some(MavMissionResult::MAV_MISSION_ACCEPTED));
        assert_eq!((done, s.circle_m()), (Some(0), Some(30.0)));
        let p = FenceParams {
            enabled: true,
            kinds: 4,
            ..FenceParams::default()
        };
        let at = |north| Ned {
            north,
            east: 0.0,
            up: 0.0,
        };
        assert_eq!(s.breach(&p, &at(110.0)), None, "inside the later circle");
        assert!(s.breach(&p, &at(0.0)).is_some(), "the earlier one is gone");

        for radius in [0.0, -5.0, f32::NAN, f32::INFINITY] {
            s.on_count(GCS, 2);
            s.on_item(GCS, vertex(&f, 0, 0.0, 0.0), &f);
            let (out, done) = s.on_item(GCS, circle(&f, 1, 0.0, 0.0, radius), &f);
            assert_eq!(
                (acked(&out), done),
                (Some(MavMissionResult::MAV_MISSION_INVALID_PARAM1), None),
                "radius {radius}"
            );
            // The transfer is over and the fence on board untouched.
            let (out, _) = s.on_item(GCS, vertex(&f, 1, 0.0, 0.0), &f);
            assert_eq!(acked(&out), Some(MavMissionResult::MAV_MISSION_DENIED));
            assert_eq!((s.vertices(), s.circle_m()), (0, Some(30.0)));
        }
    }

    #[test]
    fn polygon_and_circle_items_are_both_enforced_under_the_polygon_bit_only() {
        let f = frame();
        let mut s = FenceStore::default();
        // A 100 m square around home and a 40 m circle centred 30 m east.
        let (out, _) = transfer(
            &mut s,
            &f,
            &[
                vertex(&f, 0, -50.0, -50.0),
                vertex(&f, 1, -50.0, 50.0),
                vertex(&f, 2, 50.0, 50.0),
                vertex(&f, 3, 50.0, -50.0),
                circle(&f, 4, 0.0, 30.0, 40.0),
            ],
        );
        assert_eq!(acked(&out), Some(MavMissionResult::MAV_MISSION_ACCEPTED));
        let at = |north, east| Ned {
            north,
            east,
            up: 0.0,
        };
        let items = FenceParams {
            enabled: true,
            kinds: 4,
            ..FenceParams::default()
        };
        assert_eq!(s.breach(&items, &at(0.0, 30.0)), None);
        // Inside the circle, outside the square.
        assert_eq!(s.breach(&items, &at(0.0, 60.0)).as_deref(), Some("polygon"));
        assert_eq!(s.breach(&items, &at(0.0, 30.0)), None, "back inside");
        // Inside the square, outside the circle.
        let why = s
            .breach(&items, &at(0.0, -20.0))
            .expect("outside the circle");
        assert_eq!(why, "circle item (50 m from its centre, radius 40 m)");
        // FENCE_TYPE without bit 4 (the ceiling and FENCE_RADIUS circle only): the items are
        // not enforced.
        let mut params_only = FenceStore::default();
        transfer(&mut params_only, &f, &[circle(&f, 0, 0.0, 0.0, 10.0)]);
        let p = FenceParams {
            enabled: true,
            kinds: 1 | 2,
            radius_m: 300.0,
            alt_max_m: 100.0,
        };
        assert_eq!(params_only.breach(&p, &at(100.0, 0.0)), None);
        assert!(params_only
            .breach(&FenceParams { kinds: 7, ..p }, &at(100.0, 0.0))
            .is_some());
    }
}
