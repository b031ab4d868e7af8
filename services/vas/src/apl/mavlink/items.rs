//! USAL to MAVLink mission items and commands, pure: waypoints to mission items (frames, the
//! fly-over radius, what terrain altitudes need), a plane's landing, a DIRECTED bearing as a
//! point, speeds, sticks to RC PWM.

use super::*;

/// Where a plane's landing approach begins: this far from home, metres, on the side the plane
/// is (so it turns onto final without crossing the field)...
pub(super) const LANDING_APPROACH_M: f64 = 700.0;
/// ...at this height above home, metres (a 3.3° glide slope to the touchdown point).
pub(super) const LANDING_APPROACH_ALT_M: f32 = 40.0;

/// A plane's landing, as ArduPilot flies one: DO_LAND_START, the final approach fix on the
/// line from `home` through the plane's `position` ([`LANDING_APPROACH_M`] out,
/// [`LANDING_APPROACH_ALT_M`] up), then NAV_LAND on `home`. Item 0 is home itself
/// (ArduPilot's); the landing begins at item 1, the marker, as ArduPilot's own jump to a
/// landing sequence does.
pub(super) fn landing_mission(home: (f64, f64), position: (f64, f64)) -> Vec<MissionItem> {
    const M_PER_DEG: f64 = 111_319.49;
    let cos_lat = home.0.to_radians().cos().max(1e-6);
    let north = (position.0 - home.0) * M_PER_DEG;
    let east = (position.1 - home.1) * M_PER_DEG * cos_lat;
    let d = north.hypot(east);
    // Over home already: approach from the north.
    let (un, ue) = if d < 1.0 {
        (1.0, 0.0)
    } else {
        (north / d, east / d)
    };
    let fix = (
        home.0 + un * LANDING_APPROACH_M / M_PER_DEG,
        home.1 + ue * LANDING_APPROACH_M / (M_PER_DEG * cos_lat),
    );
    let mut land = MissionItem::waypoint(home.0, home.1, 0.0);
    land.command = MavCmd::MAV_CMD_NAV_LAND;
    let approach = MissionItem::waypoint(fix.0, fix.1, LANDING_APPROACH_ALT_M);
    vec![
        MissionItem::waypoint(home.0, home.1, 0.0),
        super::layout::land_start_item(fix.0, fix.1, approach.frame),
        approach,
        land,
    ]
}

/// Acceptance radius of a fly-over waypoint (NAV_WAYPOINT param2), metres: the vehicle
/// passes (nearly) over the point before turning. A fly-by waypoint leaves param2 at 0, so
/// the autopilot turns early by its own WP_RADIUS.
pub const FLY_OVER_RADIUS_M: f32 = 1.0;

/// The mission item for a queued waypoint.
pub(super) fn mission_item(w: &Waypoint) -> MissionItem {
    let mut item = MissionItem::waypoint(w.lat, w.lon, w.alt as f32);
    item.frame = frame_of(w.alt_ref);
    item.command = match w.kind {
        WaypointKind::Nav => MavCmd::MAV_CMD_NAV_WAYPOINT,
        WaypointKind::Takeoff => MavCmd::MAV_CMD_NAV_TAKEOFF,
        WaypointKind::Land => MavCmd::MAV_CMD_NAV_LAND,
    };
    if w.fly_over && w.kind == WaypointKind::Nav {
        item.params[1] = FLY_OVER_RADIUS_M;
    }
    item
}

/// The global frame a waypoint's altitude reference means. (The `_INT` names of these frames
/// are their deprecated synonyms for MISSION_ITEM_INT; ArduPilot reads both alike.)
pub(super) fn frame_of(r: AltRef) -> MavFrame {
    match r {
        AltRef::Msl => MavFrame::MAV_FRAME_GLOBAL,
        AltRef::Relative => MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT,
        AltRef::Terrain => MavFrame::MAV_FRAME_GLOBAL_TERRAIN_ALT,
    }
}

/// Why this autopilot cannot fly `wps` as written, if it cannot: altitudes above terrain
/// need terrain data (ArduPilot `TERRAIN_ENABLE`), which a rover, flying no altitude, never
/// needs. `terrain_enable` is the parameter's cached value.
pub(super) fn altitude_refusal(
    kind: VehicleKind,
    terrain_enable: Option<f32>,
    wps: &[Waypoint],
) -> Option<String> {
    let w = wps.iter().find(|w| w.alt_ref == AltRef::Terrain)?;
    if kind == VehicleKind::Rover || terrain_enable.is_some_and(|v| v > 0.0) {
        return None;
    }
    Some(format!(
        "waypoint {} ({}): altitude above terrain, but the autopilot has no terrain data \
         (TERRAIN_ENABLE is {}); fly the plan with altRef MSL or REL",
        w.seq,
        w.leg,
        terrain_enable.map_or_else(|| "absent".to_owned(), |v| v.to_string())
    ))
}

/// How far ahead a DIRECTED aircraft is sent along its bearing: an hour at its speed, at
/// least 2 km, so it flies the bearing until told otherwise.
pub(super) fn directed_point(from: (f64, f64), t: &DirectedTarget) -> (f64, f64) {
    let d = (f64::from(t.speed) * 3600.0).max(2000.0);
    let b = f64::from(t.bearing).to_radians();
    let m_per_deg = 111_319.49;
    let lat = from.0 + d * b.cos() / m_per_deg;
    let cos_lat = from.0.to_radians().cos().max(0.01);
    let lon = from.1 + d * b.sin() / (m_per_deg * cos_lat);
    (lat.clamp(-89.9, 89.9), lon)
}

/// The speed a waypoint asks for, m/s; 0 for the autopilot's cruise speed.
pub(super) fn wanted_speed(w: &Waypoint) -> f64 {
    if w.speed.is_finite() && w.speed > 0.0 {
        w.speed
    } else {
        0.0
    }
}

pub(super) fn same_item(a: &MissionItem, b: &MissionItem) -> bool {
    a.command == b.command && a.x == b.x && a.y == b.y && (a.z - b.z).abs() < 0.01
}

/// Joystick to RC PWM (ch1 roll/steering, ch2 pitch, ch3 throttle, ch4 yaw); `None` releases.
pub(super) fn rc_channels(kind: VehicleKind, mc: Option<&ManualControl>) -> [u16; 8] {
    let Some(mc) = mc else { return [0; 8] };
    let axis = |v: f32| {
        let v = if v.is_finite() {
            v.clamp(-1.0, 1.0)
        } else {
            0.0
        };
        (1500.0 + v * 500.0).round() as u16
    };
    let throttle = match kind {
        // A rover's throttle is centred (reverse below 1500), an aircraft's starts at 1000.
        VehicleKind::Rover => axis(mc.throttle),
        _ => axis(mc.throttle.clamp(-1.0, 1.0) * 2.0 - 1.0),
    };
    [
        axis(mc.roll),
        axis(-mc.pitch),
        throttle,
        axis(mc.yaw),
        u16::MAX,
        u16::MAX,
        u16::MAX,
        u16::MAX,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_landing_approaches_from_the_planes_side_and_lands_on_home() {
        let home = (41.275, 1.987);
        // The plane 2 km east of home: the approach fix 700 m east, 40 m up; NAV_LAND on home.
        let east = (
            41.275,
            1.987 + 2000.0 / (111_319.49 * 41.275_f64.to_radians().cos()),
        );
        let mut m = landing_mission(home, east);
        assert_eq!(m.len(), 4);
        assert_eq!(m[1].command, MavCmd::MAV_CMD_DO_LAND_START);
        let marker = m.remove(1);
        assert_eq!(m[1].command, MavCmd::MAV_CMD_NAV_WAYPOINT);
        assert_eq!((marker.x, marker.y), (m[1].x, m[1].y), "marks the approach");
        assert_eq!(m[2].command, MavCmd::MAV_CMD_NAV_LAND);
        assert_eq!(
            (m[2].lat_deg(), m[2].lon_deg()),
            (m[0].lat_deg(), m[0].lon_deg())
        );
        let fix_east = (m[1].lon_deg() - home.1) * 111_319.49 * home.0.to_radians().cos();
        let fix_north = (m[1].lat_deg() - home.0) * 111_319.49;
        assert!((fix_east - LANDING_APPROACH_M).abs() < 1.0, "{fix_east}");
        assert!(fix_north.abs() < 1.0, "{fix_north}");
        assert_eq!(m[1].z, LANDING_APPROACH_ALT_M);
        // Over home: from the north.
        let m = landing_mission(home, home);
        assert!(m[2].lat_deg() > home.0);
    }

    #[test]
    fn the_altitude_reference_chooses_the_frame_and_terrain_needs_terrain_data() {
        let mut w = Waypoint {
            lat: 41.0,
            lon: 2.0,
            alt: 634.0,
            alt_ref: AltRef::Msl,
            ..Waypoint::default()
        };
        let item = mission_item(&w);
        assert_eq!(item.frame, MavFrame::MAV_FRAME_GLOBAL);
        assert_eq!(item.z, 634.0);
        w.alt_ref = AltRef::Relative;
        assert_eq!(
            mission_item(&w).frame,
            MavFrame::MAV_FRAME_GLOBAL_RELATIVE_ALT
        );
        w.alt_ref = AltRef::Terrain;
        assert_eq!(
            mission_item(&w).frame,
            MavFrame::MAV_FRAME_GLOBAL_TERRAIN_ALT
        );
        let wps = [w];
        let why = altitude_refusal(VehicleKind::Copter, None, &wps).expect("refused");
        assert!(why.contains("TERRAIN_ENABLE"), "{why}");
        assert!(altitude_refusal(VehicleKind::Plane, Some(0.0), &wps).is_some());
        assert_eq!(altitude_refusal(VehicleKind::Plane, Some(1.0), &wps), None);
        assert_eq!(altitude_refusal(VehicleKind::Rover, None, &wps), None);
    }

    #[test]
    fn fly_over_tightens_the_acceptance_radius() {
        let mut w = Waypoint {
            lat: 41.0,
            lon: 2.0,
            ..Waypoint::default()
        };
        assert_eq!(
            mission_item(&w).params[1],
            0.0,
            "fly-by: the autopilot's WP_RADIUS"
        );
        w.fly_over = true;
        assert_eq!(mission_item(&w).params[1], FLY_OVER_RADIUS_M);
        w.kind = WaypointKind::Takeoff;
        assert_eq!(mission_item(&w).params[1], 0.0);
        assert_eq!(
            wanted_speed(&Waypoint {
                speed: f64::NAN,
                ..w.clone()
            }),
            0.0
        );
        assert_eq!(wanted_speed(&Waypoint { speed: 3.5, ..w }), 3.5);
    }

    #[test]
    fn a_directed_aircraft_is_sent_far_along_its_bearing() {
        let t = DirectedTarget {
            alt: 30.0,
            speed: 5.0,
            bearing: 90.0,
        };
        let (lat, lon) = directed_point((41.0, 2.0), &t);
        assert!((lat - 41.0).abs() < 1e-9, "{lat}");
        let east_m = (lon - 2.0) * 111_319.49 * 41f64.to_radians().cos();
        assert!((east_m - 18_000.0).abs() < 1.0, "{east_m}");
        let (lat, _) = directed_point(
            (41.0, 2.0),
            &DirectedTarget {
                bearing: 180.0,
                ..t
            },
        );
        assert!(lat < 41.0);
    }

    #[test]
    fn sticks_to_pwm() {
        let mc = ManualControl {
            roll: 1.0,
            pitch: 0.0,
            throttle: -1.0,
            yaw: f32::NAN,
            timestamp_ms: 0,
        };
        let ch = rc_channels(VehicleKind::Rover, Some(&mc));
        assert_eq!(&ch[..4], &[2000, 1500, 1000, 1500]);
        let ch = rc_channels(VehicleKind::Copter, Some(&mc));
        assert_eq!(ch[2], 1000);
        assert_eq!(rc_channels(VehicleKind::Rover, None), [0; 8]);
    }
}
