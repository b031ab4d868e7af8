//! The plan's geofence (issue 15 item 5): `<fence>` says where the vehicle must stay (a
//! maximum distance and height from home, and/or an inclusion polygon). A plan whose nominal
//! waypoints, or the straight tracks between them, leave it is refused with the line and
//! column of the leg that leaves; so is a change (modified leg, inserted legs, re-task). The
//! service hands the fence to the VAS (`set_fence`), which checks every waypoint pushed
//! (branches the nominal expansion does not take are caught there) and uploads it to the
//! autopilot, which enforces it on the vehicle.
//!
//! The home the distance is measured from is the fence's `homeLat`/`homeLon`, else the plan's
//! first waypoint (a rover's departure starts at home). Heights are compared for `REL` and
//! `AGL` plans (above home; the FPMa knows no terrain); an `MSL` plan's heights are left to
//! the autopilot, which knows its home altitude.

use crate::exec::expand_nominal;
use crate::expand::Waypoint;
use crate::model::FlightPlan;
use crate::parse::{PlanError, PlanErrorKind};
use crate::vehicle::VehicleParams;

/// Resolves the fence's home (when the plan does not give it) and checks the plan's nominal
/// waypoints against the fence.
///
/// # Errors
/// [`PlanErrorKind::OutsideFence`] at the leg that leaves, or the expansion's own error at the
/// fence element.
pub fn resolve_and_check(plan: &mut FlightPlan, vehicle: &VehicleParams) -> Result<(), PlanError> {
    let Some(pf) = &plan.fence else {
        return Ok(());
    };
    let at_fence = |kind| PlanError::at_line(pf.line, pf.col, kind);
    let wps = expand_nominal(plan.clone(), vehicle.clone())
        .map_err(|e| at_fence(PlanErrorKind::Structure(e.to_string())))?;
    if !pf.home_given {
        let home = wps.first().map(|w| (w.lat, w.lon));
        if let (Some(home), Some(pf)) = (home, plan.fence.as_mut()) {
            pf.fence.home = home;
        }
    }
    check_waypoints(plan, &wps)
}

/// Checks `wps` (from `plan`, in flying order) against the plan's fence.
///
/// # Errors
/// [`PlanErrorKind::OutsideFence`] at the line of the leg that leaves (the fence element's
/// for legs built in flight, which have no line).
pub fn check_waypoints(plan: &FlightPlan, wps: &[Waypoint]) -> Result<(), PlanError> {
    let Some(pf) = &plan.fence else {
        return Ok(());
    };
    let relative = !matches!(plan.altitude_reference(), usal_types::AltRef::Msl);
    let mut prev: Option<(f64, f64)> = None;
    for w in wps {
        let p = (w.lat, w.lon);
        let r = pf
            .fence
            .check_point(p, relative.then_some(w.alt))
            .and_then(|()| prev.map_or(Ok(()), |a| pf.fence.check_segment(a, p)));
        if let Err(why) = r {
            let (line, col) = plan
                .find(&w.leg)
                .filter(|n| n.line > 0)
                .map_or((pf.line, pf.col), |n| (n.line, n.col));
            return Err(PlanError::at_line(
                line,
                col,
                PlanErrorKind::OutsideFence {
                    leg: w.leg.clone(),
                    why,
                },
            ));
        }
        prev = Some(p);
    }
    Ok(())
}

/// Checks a changed plan: its nominal expansion from the start (the fence's home stays).
///
/// # Errors
/// As [`check_waypoints`].
pub fn check_plan(plan: &FlightPlan, vehicle: &VehicleParams) -> Result<(), PlanError> {
    let Some(pf) = &plan.fence else {
        return Ok(());
    };
    let wps = expand_nominal(plan.clone(), vehicle.clone()).map_err(|e| {
        PlanError::at_line(pf.line, pf.col, PlanErrorKind::Structure(e.to_string()))
    })?;
    check_waypoints(plan, &wps)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::parse::parse_plan;

    const PLAN: &str = r#"<flightPlan name="f" vehicle="rover" altRef="REL">
  <fixes>
    <fix id="HOME" lat="41.27500" lon="1.98700" alt="0"/>
    <fix id="A" lat="41.27540" lon="1.98700" alt="0"/>
    <fix id="FAR" lat="41.27700" lon="1.98700" alt="0"/>
  </fixes>
  <mission>
    <leg type="IF" fix="HOME"/>
    <leg id="a" type="TF" fix="A"/>
    <leg id="far" type="TF" fix="FAR"/>
  </mission>
  <fence maxDistance="100" action="hold"/>
</flightPlan>"#;

    #[test]
    fn a_plan_crossing_the_fence_is_refused_at_the_leg_that_leaves() {
        let e = parse_plan(PLAN, &VehicleParams::rover()).unwrap_err();
        assert_eq!((e.line, e.col), (10, 5), "{e}");
        let text = e.to_string();
        assert!(
            text.contains("leg `far` leaves the fence") && text.contains("(fence: 100 m)"),
            "{text}"
        );
        let ok = PLAN.replace(r#"<leg id="far" type="TF" fix="FAR"/>"#, "");
        let plan = parse_plan(&ok, &VehicleParams::rover()).unwrap();
        let f = plan.fence.unwrap();
        assert_eq!(f.fence.home, (41.275, 1.987), "home: the first waypoint");
        assert_eq!(f.fence.action, usal_types::FenceAction::Hold);
    }

    #[test]
    fn changes_that_leave_the_fence_are_refused_and_change_nothing() {
        let ok = PLAN.replace(r#"<leg id="far" type="TF" fix="FAR"/>"#, "");
        let plan = parse_plan(&ok, &VehicleParams::rover()).unwrap();
        let mut ex = crate::exec::Executive::new(plan, VehicleParams::rover());
        let v = ex.version();
        let e = ex.insert_legs(r#"<leg type="TF" fix="FAR"/>"#).unwrap_err();
        assert!(e.to_string().contains("leaves the fence"), "{e}");
        let e = ex
            .modify_leg("a", &[("fix".into(), "FAR".into())])
            .unwrap_err();
        assert!(e.to_string().contains("leg `a` leaves the fence"), "{e}");
        assert_eq!(ex.version(), v, "nothing changed");
        assert!(ex.insert_legs(r#"<leg type="TF" fix="HOME"/>"#).is_ok());
    }

    #[test]
    fn bad_fences_are_refused_with_their_position() {
        for (fence, what) in [
            ("<fence/>", "set maxDistance"),
            (r#"<fence maxDistance="-3"/>"#, "maxDistance"),
            (
                r#"<fence maxDistance="50" homeLat="41"/>"#,
                "both homeLat and homeLon",
            ),
            (
                r#"<fence maxDistance="50" action="land"/>"#,
                "`report`, `rtl` or `hold`",
            ),
            (
                r#"<fence><pt lat="41.2749" lon="1.9869"/><pt lat="41.2760" lon="1.9869"/></fence>"#,
                "at least 3",
            ),
            (
                r#"<fence><pt lat="41.274" lon="1.986"/><pt lat="41.276" lon="1.988"/><pt lat="41.276" lon="1.986"/><pt lat="41.274" lon="1.988"/></fence>"#,
                "self-intersects",
            ),
        ] {
            let plan = PLAN.replace(r#"<fence maxDistance="100" action="hold"/>"#, fence);
            let e = parse_plan(&plan, &VehicleParams::rover()).unwrap_err();
            assert_eq!(e.line, 12, "{fence}: {e}");
            assert!(e.to_string().contains(what), "{fence}: {e}");
        }
    }
}
