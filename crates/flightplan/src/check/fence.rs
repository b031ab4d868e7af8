//! The plan's geofence: `<fence>` says where the vehicle must stay (a
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

use crate::expand::Waypoint;
use crate::model::FlightPlan;
use crate::parse::{PlanError, PlanErrorKind};

/// Gives a fence written without `homeLat`/`homeLon` the plan's first waypoint as its home.
pub fn resolve_home(plan: &mut FlightPlan, nominal: &[Waypoint]) {
    if let (Some(pf), Some(first)) = (plan.fence.as_mut(), nominal.first()) {
        if !pf.home_given {
            pf.fence.home = (first.lat, first.lon);
        }
    }
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

#[cfg(test)]
mod tests {
    use crate::check::{load, CheckError};
    use crate::exec::Executive;
    use crate::parse::PlanError;
    use crate::vehicle::VehicleParams;

    fn refusal(src: &str) -> PlanError {
        match load(src, &VehicleParams::rover()) {
            Err(CheckError::Plan(e)) => e,
            other => panic!("expected a refusal with a position, got {other:?}"),
        }
    }

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
        let e = refusal(PLAN);
        assert_eq!((e.line, e.col), (10, 5), "{e}");
        let text = e.to_string();
        assert!(
            text.contains("leg `far` leaves the fence") && text.contains("(fence: 100 m)"),
            "{text}"
        );
        let ok = PLAN.replace(r#"<leg id="far" type="TF" fix="FAR"/>"#, "");
        let plan = load(&ok, &VehicleParams::rover()).unwrap();
        let f = plan.plan().fence.clone().unwrap();
        assert_eq!(f.fence.home, (41.275, 1.987), "home: the first waypoint");
        assert_eq!(f.fence.action, usal_types::FenceAction::Hold);
    }

    #[test]
    fn changes_that_leave_the_fence_are_refused_and_change_nothing() {
        let ok = PLAN.replace(r#"<leg id="far" type="TF" fix="FAR"/>"#, "");
        let mut ex = Executive::from_checked(load(&ok, &VehicleParams::rover()).unwrap());
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
            let e = refusal(&plan);
            assert_eq!(e.line, 12, "{fence}: {e}");
            assert!(e.to_string().contains(what), "{fence}: {e}");
        }
    }
}
