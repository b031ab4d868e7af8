//! The flight-state transition tables per vehicle kind (003 §3.3.1, figure 3.6; §6.2.2) and
//! the command checker that refuses a transition with its reason (seed 000).
//!
//! The rover's "special" transitions are all allowed, as 003 §6.2.2 found necessary (parking
//! straight to automatic navigation), except out of MANUAL, the failsafe state, which has no
//! way back to navigation. Aircraft must take off before navigating and land before parking.

use usal_types::{FlightState, VehicleKind};

use FlightState::*;

const ROVER: &[(FlightState, &[FlightState])] = &[
    (ConfigureCheck, &[Parking, Manual]),
    (
        Parking,
        &[Directed, ManualNavigation, WaypointNavigation, Manual],
    ),
    (
        Directed,
        &[Parking, ManualNavigation, WaypointNavigation, Manual],
    ),
    (
        ManualNavigation,
        &[Parking, Directed, WaypointNavigation, Manual],
    ),
    (
        WaypointNavigation,
        &[Parking, Directed, ManualNavigation, Manual],
    ),
    (Manual, &[]),
];

const AIRCRAFT: &[(FlightState, &[FlightState])] = &[
    (ConfigureCheck, &[Parking, Manual]),
    (Parking, &[TakeOff, Manual]),
    (
        TakeOff,
        &[
            Directed,
            WaypointNavigation,
            Landing,
            ReturnToLaunch,
            Manual,
        ],
    ),
    (
        Directed,
        &[
            ManualNavigation,
            WaypointNavigation,
            Landing,
            ReturnToLaunch,
            Manual,
        ],
    ),
    (
        ManualNavigation,
        &[
            Directed,
            WaypointNavigation,
            Landing,
            ReturnToLaunch,
            Manual,
        ],
    ),
    (
        WaypointNavigation,
        &[Directed, ManualNavigation, Landing, ReturnToLaunch, Manual],
    ),
    (
        ReturnToLaunch,
        &[Directed, WaypointNavigation, Landing, Manual],
    ),
    (Landing, &[Parking, Directed, Manual]),
    (Manual, &[]),
];

fn table(kind: VehicleKind) -> &'static [(FlightState, &'static [FlightState])] {
    match kind {
        VehicleKind::Rover => ROVER,
        VehicleKind::Copter | VehicleKind::Plane => AIRCRAFT,
    }
}

/// The states reachable from `from` by request.
pub fn allowed(kind: VehicleKind, from: FlightState) -> &'static [FlightState] {
    table(kind)
        .iter()
        .find(|(s, _)| *s == from)
        .map_or(&[], |(_, to)| to)
}

/// Checks a requested transition against the table.
///
/// # Errors
/// The reason for a refusal, for the caller (the operator) to read.
pub fn check(kind: VehicleKind, from: FlightState, to: FlightState) -> Result<(), String> {
    if !to.applies_to(kind) {
        return Err(format!("{to} is not a state of a {kind}"));
    }
    if from == to {
        return Err(format!("already in {to}"));
    }
    let next = allowed(kind, from);
    if next.contains(&to) {
        return Ok(());
    }
    if from == Manual {
        return Err(format!(
            "no transition from {from} to {to}: MANUAL is the failsafe state, the RC pilot keeps control"
        ));
    }
    let names: Vec<&str> = next.iter().map(|s| s.name()).collect();
    Err(format!(
        "no transition from {from} to {to} for a {kind} (allowed: {})",
        names.join(", ")
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tables_only_name_states_of_their_vehicle() {
        for kind in [VehicleKind::Rover, VehicleKind::Copter, VehicleKind::Plane] {
            for (from, to) in table(kind) {
                assert!(from.applies_to(kind));
                assert!(to.iter().all(|s| s.applies_to(kind) && s != from));
            }
        }
    }

    #[test]
    fn rover_parks_straight_into_navigation() {
        let k = VehicleKind::Rover;
        assert_eq!(check(k, Parking, WaypointNavigation), Ok(()));
        assert_eq!(check(k, WaypointNavigation, Parking), Ok(()));
        assert_eq!(check(k, ConfigureCheck, Parking), Ok(()));
    }

    #[test]
    fn refusals_say_why() {
        let k = VehicleKind::Rover;
        assert_eq!(
            check(k, Parking, TakeOff).unwrap_err(),
            "TAKE_OFF is not a state of a rover"
        );
        assert!(check(k, ConfigureCheck, WaypointNavigation)
            .unwrap_err()
            .contains("allowed: PARKING, MANUAL"));
        assert!(check(k, Manual, Parking).unwrap_err().contains("failsafe"));
        assert_eq!(
            check(k, Parking, Parking).unwrap_err(),
            "already in PARKING"
        );
        let c = VehicleKind::Copter;
        assert!(check(c, Parking, WaypointNavigation).is_err());
        assert_eq!(check(c, Parking, TakeOff), Ok(()));
        assert_eq!(check(c, Landing, Parking), Ok(()));
    }
}
