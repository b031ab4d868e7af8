//! The geofence on the VAS side: pushed waypoints, and the straight tracks between consecutive
//! ones, must stay inside the fence in force: the vehicle's own (`<fence>` in the VAS file or
//! `--fence`, what `usal run` gives from the mission), narrowed by the plan's (`set_fence`; a
//! plan's fence may only narrow the vehicle's, and a plan without one leaves the vehicle's in
//! force). A refusal names the waypoint like the other limits (`limits.rs`). The fence also
//! goes to the autopilot (`IAutopilot::upload_fence`), which enforces it on the vehicle
//! itself; until the autopilot took it the vehicle does not start ([`Onboard`]).
//!
//! Heights are checked where the waypoint's altitude is above home (`REL`, and `AGL`, whose
//! terrain the VAS does not know, conservatively as above home); an `MSL` altitude is left to
//! the autopilot, which knows its home altitude.

use usal_types::{AltRef, Fence, FlightState, Waypoint};

/// Whether the fence in force is on the autopilot: a vehicle with a fence starts only once the
/// autopilot took it.
#[derive(Clone, Debug, PartialEq)]
pub enum Onboard {
    /// No fence is in force.
    NoFence,
    /// The fence in force is being uploaded.
    Uploading,
    /// The autopilot took the fence in force.
    Taken,
    /// The autopilot did not take it: why.
    Refused(String),
}

impl Onboard {
    /// Where the fence stands before the first upload.
    pub fn initial(fence: Option<&Fence>) -> Self {
        if fence.is_some() {
            Self::Uploading
        } else {
            Self::NoFence
        }
    }

    /// Checks a change from `from` to `to`: starting to move on its own (take-off, waypoint
    /// navigation, a directed target, from any other state) needs the fence on the autopilot.
    ///
    /// # Errors
    /// Why the vehicle may not start, e.g. `cannot go to WAYPOINT_NAVIGATION: the autopilot
    /// did not take the fence (...)`.
    pub fn may_start(&self, from: FlightState, to: FlightState) -> Result<(), String> {
        use FlightState::{Directed, TakeOff, WaypointNavigation};
        let moving = |s| matches!(s, TakeOff | WaypointNavigation | Directed);
        if !moving(to) || moving(from) {
            return Ok(());
        }
        match self {
            Self::NoFence | Self::Taken => Ok(()),
            Self::Uploading => Err(format!(
                "cannot go to {to}: the fence is still being uploaded to the autopilot"
            )),
            Self::Refused(why) => Err(format!(
                "cannot go to {to}: the autopilot did not take the fence ({why}); the vehicle \
                 does not start without it"
            )),
        }
    }
}

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
    fn a_vehicle_starts_only_with_its_fence_on_the_autopilot() {
        use FlightState::*;
        let refused = Onboard::Refused("NO_SPACE".into());
        let e = refused.may_start(Parking, WaypointNavigation).unwrap_err();
        assert!(e.contains("did not take the fence (NO_SPACE)"), "{e}");
        assert!(refused.may_start(Parking, TakeOff).is_err());
        assert!(refused.may_start(Manual, Directed).is_err());
        let e = Onboard::Uploading
            .may_start(Parking, WaypointNavigation)
            .unwrap_err();
        assert!(e.contains("still being uploaded"), "{e}");
        // Stopping, the pilot's own driving and a vehicle already moving are never held.
        assert!(refused.may_start(WaypointNavigation, Parking).is_ok());
        assert!(refused.may_start(Parking, ManualNavigation).is_ok());
        assert!(refused.may_start(WaypointNavigation, Directed).is_ok());
        for ok in [Onboard::NoFence, Onboard::Taken] {
            assert!(ok.may_start(Parking, WaypointNavigation).is_ok());
        }
        assert_eq!(Onboard::initial(None), Onboard::NoFence);
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
