//! The waypoint stream a plan gives with no in-flight change, computed by running the executive
//! on its own (its holds and waiting loops flown once): how uploads are checked to end, and what
//! stations draw.

use super::types::ExpandError;
use super::Executive;
use crate::expand::*;
use crate::model::*;
use crate::vehicle::VehicleParams;
use std::sync::Arc;

/// Steps a simulation takes before giving up on a plan that does not end.
pub(super) const SIM_LIMIT: usize = 1_000_000;

/// The waypoint stream the executive produces with no in-flight changes: holds and loops that
/// wait for a command or a condition are flown once and their waypoints marked `waits`.
///
/// # Errors
/// [`ExpandError::Endless`] for a plan that does not end.
pub fn expand_nominal(
    plan: impl Into<Arc<FlightPlan>>,
    vehicle: VehicleParams,
) -> Result<Vec<Waypoint>, ExpandError> {
    let mut ex = Executive::new(plan, vehicle);
    ex.nominal = true;
    ex.simulating = true;
    ex.settle();
    let mut out = Vec::new();
    while let Some(w) = ex.head().cloned() {
        if out.len() >= SIM_LIMIT {
            return Err(ExpandError::Endless(SIM_LIMIT));
        }
        let mut w = w;
        w.seq = ex.next_seq;
        w.version = ex.version;
        out.push(w);
        ex.reach_head();
    }
    Ok(out)
}
