//! Flight plans: XML flight plans → validated model → waypoint stream, the executive that flies
//! it and takes changes in flight, and the wire types of the services that fly plans (the
//! FPMa's `api`, the fleet layer's `fleet_api`). The FPMa (`fpma`) is the service around it;
//! the FPMo, the fleet layer and `usal` read plans and those types here.
//!
//! Layers, each using only those above: `xml` (plan wording over `marea::xml`) → `expr`, `geo`,
//! `vehicle` → `model` → `parse` (`parse/{error,attrs,legs}`: the document, no vehicle),
//! `polygon` → `expand`, `eta` → `exec` and `check` (one layer: the check flies a plan once in
//! the executive; the executive checks each change), `aircraft` (an aircraft's take-off,
//! climb and touchdown against its plan) → `qgc` → `plan_file` → `api`, `fleet_api` → `fuzzing`. Everything is pure (no I/O, no clock, no
//! network: the FPMa's `service` is). `tests/layering.rs` keeps the table true. See
//! `services/fpma/README.md` for the format, the API and the service's items.
//!
//! A plan is parsed, then checked once for a vehicle ([`check::load`] does both); the checked
//! plan carries its nominal waypoint stream, and only a checked plan starts an executive:
//!
//! ```
//! use flightplan::{check, exec::Executive, vehicle::VehicleParams};
//! let xml = r#"<flightPlan><fixes><fix id="A" lat="41.275" lon="1.987"/>
//!   <fix id="B" lat="41.2754" lon="1.987"/></fixes>
//!   <mission><leg type="IF" fix="A"/><leg type="TF" fix="B"/></mission></flightPlan>"#;
//! let plan = check::load(xml, &VehicleParams::rover()).unwrap();
//! assert_eq!(plan.nominal().len(), 2);
//! let mut ex = Executive::from_checked(plan);
//! let next = ex.next_waypoints(2);
//! assert_eq!(next.len(), 2);
//! ex.waypoint_reached(next[0].version, next[0].seq).unwrap();
//! assert_eq!(ex.next_waypoints(2)[0].leg, "mission.2");
//! ```
pub mod aircraft;
pub mod api;
pub mod check;
pub mod eta;
pub mod exec;
pub mod expand;
pub mod expr;
pub mod fleet_api;
#[cfg(feature = "fuzzing")]
pub mod fuzzing;
pub mod geo;
pub mod model;
pub mod parse;
pub mod plan_file;
pub mod polygon;
pub mod qgc;
pub mod vehicle;
pub mod xml;
