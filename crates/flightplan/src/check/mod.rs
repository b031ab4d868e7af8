//! One validation pass: a parsed plan becomes a [`CheckedPlan`], the only kind the executive
//! flies. The pass checks what depends on the vehicle (`vehicle`: spacings and widths against
//! its turn radius and minimum waypoint distance), flies the plan once in simulation (it must
//! end within the executive's step limit), and checks that nominal stream against the plan's
//! fence (`fence`). The stream is kept: stations draw it, the launcher measures it, the fleet
//! routes with it, so nobody simulates the same plan again.
//!
//! The parser ([`crate::parse`]) calls nothing here. The executive does: a change in flight
//! (a modified leg, inserted legs, a re-task) is checked as a whole changed plan
//! ([`check_change`]), so `check` and `exec` are one layer.

pub mod fence;
mod vehicle;

use vehicle::check_leg_lengths;
pub use vehicle::{check_vehicle, MAX_SCAN_TRACKS};

use crate::exec::{expand_nominal, ExpandError};
use crate::expand::Waypoint;
use crate::model::FlightPlan;
use crate::parse::{parse_plan, PlanError};
use crate::vehicle::VehicleParams;
use std::sync::Arc;
use thiserror::Error;

/// Why a plan cannot be flown.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum CheckError {
    /// The plan does not parse, does not suit the vehicle or leaves its fence: where and what.
    #[error(transparent)]
    Plan(#[from] PlanError),
    /// The plan does not end.
    #[error(transparent)]
    Endless(#[from] ExpandError),
}

impl CheckError {
    /// The error as a message about `file`: `file:line:col: what`, or `file: what` for a plan
    /// that does not end (it has no one position).
    pub fn in_file(&self, file: &str) -> String {
        match self {
            CheckError::Plan(e) => format!("{file}:{e}"),
            CheckError::Endless(e) => format!("{file}: {e}"),
        }
    }
}

/// A plan checked for a vehicle, with its nominal waypoint stream (flown once, as the executive
/// flies it with no change in flight).
#[derive(Clone, Debug)]
pub struct CheckedPlan {
    plan: Arc<FlightPlan>,
    vehicle: VehicleParams,
    nominal: Arc<[Waypoint]>,
}

impl CheckedPlan {
    /// The plan (its fence's home resolved).
    pub fn plan(&self) -> &FlightPlan {
        &self.plan
    }

    /// The vehicle it was checked for.
    pub fn vehicle(&self) -> &VehicleParams {
        &self.vehicle
    }

    /// The nominal waypoint stream: holds and loops that wait for a command or a condition flown
    /// once, their waypoints marked `waits`.
    pub fn nominal(&self) -> &Arc<[Waypoint]> {
        &self.nominal
    }

    /// The plan, the vehicle and the nominal stream.
    pub fn into_parts(self) -> (Arc<FlightPlan>, VehicleParams, Arc<[Waypoint]>) {
        (self.plan, self.vehicle, self.nominal)
    }
}

/// Parses `src` and checks it for `vehicle`: what a plan load is.
///
/// # Errors
/// The first problem found: [`CheckError::Plan`] with its line and column, or
/// [`CheckError::Endless`].
pub fn load(src: &str, vehicle: &VehicleParams) -> Result<CheckedPlan, CheckError> {
    check(parse_plan(src)?, vehicle)
}

/// Checks a new plan for `vehicle`. A fence without its own home gets the plan's first
/// waypoint (a rover's departure starts at home).
///
/// # Errors
/// As [`load`].
pub fn check(plan: FlightPlan, vehicle: &VehicleParams) -> Result<CheckedPlan, CheckError> {
    checked(plan, vehicle, true)
}

/// Checks a plan changed in flight: as [`check`], but the fence's home stays where it was.
///
/// # Errors
/// As [`load`].
pub fn check_change(plan: FlightPlan, vehicle: &VehicleParams) -> Result<CheckedPlan, CheckError> {
    checked(plan, vehicle, false)
}

fn checked(
    plan: FlightPlan,
    vehicle: &VehicleParams,
    resolve_home: bool,
) -> Result<CheckedPlan, CheckError> {
    check_vehicle(&plan, vehicle)?;
    // The simulation shares the plan; it is the only other holder, gone once it returns.
    let shared = Arc::new(plan);
    let nominal = expand_nominal(Arc::clone(&shared), vehicle.clone())?;
    let mut plan = Arc::try_unwrap(shared).unwrap_or_else(|p| (*p).clone());
    if resolve_home {
        fence::resolve_home(&mut plan, &nominal);
    }
    fence::check_waypoints(&plan, &nominal)?;
    check_leg_lengths(&plan, &nominal, vehicle)?;
    Ok(CheckedPlan {
        plan: Arc::new(plan),
        vehicle: vehicle.clone(),
        nominal: nominal.into(),
    })
}
