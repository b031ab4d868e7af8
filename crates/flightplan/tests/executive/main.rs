//! The executive driven like the service will drive it: waypoint-reached reports, variables set
//! mid-run and every in-flight command, checking the exact waypoints that come next.
//!
//! This file holds the test plan and the helpers; the tests are grouped by concern: `flow`
//! (loops, alternatives, emergency rules, progress, events, example plans, nominal expansion),
//! `holds` (plan holds and hold-here), `commands` (every in-flight command, its validation and
//! its effect) and `fuzz` (random command sequences never panic).

mod commands;
mod flow;
mod fuzz;
mod holds;

use flightplan::check;
use flightplan::exec::*;
use flightplan::expand::{enforce_min_distance, expand_scan, Ctx, Origin, Waypoint};
use flightplan::expr::Value;
use flightplan::geo::{distance, GeoPoint};
use flightplan::model::{NodeKind, Stage};
use flightplan::parse::parse_plan;
use flightplan::vehicle::VehicleParams;

/// Fixes 40-odd metres apart around the car park.
const FIXES: &str = r#"
  <fixes>
    <fix id="A" lat="41.27500" lon="1.98700" alt="0"/>
    <fix id="B" lat="41.27540" lon="1.98700" alt="0"/>
    <fix id="C" lat="41.27540" lon="1.98750" alt="0"/>
    <fix id="D" lat="41.27500" lon="1.98750" alt="0"/>
    <fix id="E" lat="41.27470" lon="1.98720" alt="0"/>
    <fix id="H" lat="41.27600" lon="1.98700" alt="0"/>
  </fixes>"#;

fn plan(vars: &str, body: &str) -> String {
    format!(
        r#"<flightPlan name="t" defaultSpeed="2"><variables>{vars}</variables>{FIXES}
  <departure><leg type="IF" fix="A"/></departure>
  <mission>{body}</mission>
  <approach><leg id="app" type="TF" fix="E"/></approach>
  <emergency name="low" on="battery &lt; 20" action="goto-stage" stage="approach"/>
</flightPlan>"#
    )
}

fn exec(vars: &str, body: &str) -> Executive {
    let p = check::load(&plan(vars, body), &VehicleParams::rover()).expect("test plan loads");
    Executive::from_checked(p)
}

fn fix(id: &str) -> GeoPoint {
    match id {
        "A" => GeoPoint::new(41.275, 1.987),
        "B" => GeoPoint::new(41.2754, 1.987),
        "C" => GeoPoint::new(41.2754, 1.9875),
        "D" => GeoPoint::new(41.275, 1.9875),
        "E" => GeoPoint::new(41.2747, 1.9872),
        "H" => GeoPoint::new(41.276, 1.987),
        _ => unreachable!(),
    }
}

/// The fix each of the next `n` waypoints sits on ("?" when none), for compact assertions.
fn next_fixes(ex: &Executive, n: usize) -> Vec<String> {
    ex.next_waypoints(n)
        .iter()
        .map(|w| {
            ["A", "B", "C", "D", "E", "H"]
                .iter()
                .find(|f| distance(fix(f), w.pos()) < 0.01)
                .map_or_else(|| "?".to_string(), |f| f.to_string())
        })
        .collect()
}

fn legs(ws: &[Waypoint]) -> Vec<&str> {
    ws.iter().map(|w| w.leg.as_str()).collect()
}

/// Reports the next waypoint reached.
fn reach(ex: &mut Executive) -> Waypoint {
    let w = ex.next_waypoints(1).pop().expect("a waypoint to reach");
    ex.waypoint_reached(w.version, w.seq)
        .expect("report accepted");
    w
}

fn events(ex: &mut Executive) -> Vec<EventKind> {
    ex.take_events().into_iter().map(|e| e.kind).collect()
}
