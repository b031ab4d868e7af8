//! The geofence on the VAS side (issue 15 item 5): pushed waypoints, and the straight tracks
//! between consecutive ones, must stay inside the fence the FPMa set with the plan
//! (`set_fence`) or the VAS's own configuration (`<fence>` in the VAS file). A refusal names
//! the waypoint like the other limits (`limits.rs`). The fence also goes to the autopilot
//! (`IAutopilot::upload_fence`), which enforces it on the vehicle itself.
//!
//! Heights are checked where the waypoint's altitude is above home (`REL`, and `AGL`, whose
//! terrain the VAS does not know, conservatively as above home); an `MSL` altitude is left to
//! the autopilot, which knows its home altitude.

use usal_types::{AltRef, Fence, Waypoint};

/// Checks `wps` against `fence`.
///
/// # Errors
/// The first waypoint or track outside, e.g. `waypoint 2 (seq 14) outside the fence:
/// 41.280000,1.990000 is 612 m from home (fence: 500 m)`.
pub fn check_waypoints(fence: &Fence, wps: &[Waypoint]) -> Result<(), String> {
    let mut prev: Option<(f64, f64)> = None;
    for (i, w) in wps.iter().enumerate() {
        let height = match w.alt_ref {
            AltRef::Msl => None,
            _ => Some(w.alt),
        };
        let p = (w.lat, w.lon);
        fence
            .check_point(p, height)
            .map_err(|e| format!("waypoint {i} (seq {}) outside the fence: {e}", w.seq))?;
        if let Some(a) = prev {
            fence
                .check_segment(a, p)
                .map_err(|e| format!("waypoint {i} (seq {}) outside the fence: {e}", w.seq))?;
        }
        prev = Some(p);
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use usal_types::FenceAction;

    fn wp(seq: u64, lat: f64, lon: f64, alt: f64) -> Waypoint {
        Waypoint {
            seq,
            lat,
            lon,
            alt,
            alt_ref: AltRef::Relative,
            ..Waypoint::default()
        }
    }

    #[test]
    fn waypoints_outside_the_fence_are_refused_naming_the_waypoint() {
        let f = Fence {
            home: (41.275, 1.987),
            max_distance_m: Some(100.0),
            max_height_m: Some(20.0),
            polygon: vec![],
            action: FenceAction::Hold,
        };
        let inside = wp(1, 41.2755, 1.9875, 5.0);
        assert!(check_waypoints(&f, std::slice::from_ref(&inside)).is_ok());
        let far = wp(2, 41.2770, 1.9870, 5.0);
        let e = check_waypoints(&f, &[inside.clone(), far]).unwrap_err();
        assert!(
            e.starts_with("waypoint 1 (seq 2) outside the fence:"),
            "{e}"
        );
        assert!(e.contains("m from home (fence: 100 m)"), "{e}");
        let high = wp(3, 41.2755, 1.9875, 25.0);
        let e = check_waypoints(&f, &[high]).unwrap_err();
        assert!(e.contains("25 m above home"), "{e}");
        // MSL altitudes are left to the autopilot.
        let mut msl = wp(4, 41.2755, 1.9875, 600.0);
        msl.alt_ref = AltRef::Msl;
        assert!(check_waypoints(&f, &[msl]).is_ok());
    }
}
