//! The flight-state transition tables per vehicle kind (003 §3.3.1, figure 3.6; §6.2.2) and
//! the command checker that refuses a transition with its reason (seed 000).
//!
//! The rover's "special" transitions are all allowed, as 003 §6.2.2 found necessary (parking
//! straight to automatic navigation), except out of MANUAL, the failsafe state, which has no
//! way back to navigation. Aircraft must take off before navigating and land before parking.
//! Every kind may return to launch.
//!
//! Commands that are not state changes ([`VehicleCommand`]: ARM, DISARM, DIRECTED with its
//! altitude, speed and bearing) go through the same checker ([`check_command`]), as seed 000's
//! command rules map each command onto the states it passes through.

use usal_types::{AllowedChanges, DirectedTarget, FlightState, VehicleCommand, VehicleKind};

use FlightState::*;

const ROVER: &[(FlightState, &[FlightState])] = &[
    (ConfigureCheck, &[Parking, Manual]),
    (
        Parking,
        &[
            Directed,
            ManualNavigation,
            WaypointNavigation,
            ReturnToLaunch,
            Manual,
        ],
    ),
    (
        Directed,
        &[
            Parking,
            ManualNavigation,
            WaypointNavigation,
            ReturnToLaunch,
            Manual,
        ],
    ),
    (
        ManualNavigation,
        &[
            Parking,
            Directed,
            WaypointNavigation,
            ReturnToLaunch,
            Manual,
        ],
    ),
    (
        WaypointNavigation,
        &[Parking, Directed, ManualNavigation, ReturnToLaunch, Manual],
    ),
    (
        ReturnToLaunch,
        &[
            Parking,
            Directed,
            ManualNavigation,
            WaypointNavigation,
            Manual,
        ],
    ),
    (Manual, &[]),
];

/// Copters and planes (TAXI is a plane's only: [`allowed`] leaves it out for a copter).
const AIRCRAFT: &[(FlightState, &[FlightState])] = &[
    (ConfigureCheck, &[Parking, Manual]),
    (Parking, &[TakeOff, Taxi, Manual]),
    // On the ground: back to parking, or onto the runway and off.
    (Taxi, &[Parking, TakeOff, Manual]),
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

/// The states reachable from `from` by request (those a vehicle of `kind` has).
pub fn allowed(kind: VehicleKind, from: FlightState) -> Vec<FlightState> {
    table(kind)
        .iter()
        .find(|(s, _)| *s == from)
        .map_or(&[][..], |(_, to)| to)
        .iter()
        .copied()
        .filter(|s| s.applies_to(kind))
        .collect()
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

/// Where the motors may be armed or disarmed: parked (a rover also while its RC pilot drives
/// it in DIRECTED, which is the RC transmitter's MANUAL mode).
fn on_the_ground(kind: VehicleKind, from: FlightState) -> bool {
    from == Parking || (kind == VehicleKind::Rover && from == Directed)
}

/// Checks a command against the present state (and arming).
///
/// # Errors
/// The reason for a refusal, naming the state, the command and why.
pub fn check_command(
    kind: VehicleKind,
    from: FlightState,
    armed: bool,
    cmd: &VehicleCommand,
) -> Result<(), String> {
    if from == Manual {
        return Err(format!(
            "{cmd} refused in {from}: MANUAL is the failsafe state, the RC pilot keeps control"
        ));
    }
    if from == ConfigureCheck {
        return Err(format!(
            "{cmd} refused in {from}: the autopilot is still being configured"
        ));
    }
    match cmd {
        VehicleCommand::Arm | VehicleCommand::Disarm => {
            let arm = matches!(cmd, VehicleCommand::Arm);
            if !on_the_ground(kind, from) {
                let why = if arm {
                    "arming happens parked, before moving off"
                } else {
                    "the motors keep the vehicle under control; go to PARKING (or land) first"
                };
                return Err(format!("{cmd} refused in {from} for a {kind}: {why}"));
            }
            if arm && kind == VehicleKind::Copter {
                return Err(format!(
                    "{cmd} refused in {from} for a copter: it arms as it takes off (TAKE_OFF); \
                     parked it is in LAND, where ArduCopter does not arm"
                ));
            }
            if armed == arm {
                let already = if arm { "armed" } else { "disarmed" };
                return Err(format!("{cmd} refused in {from}: already {already}"));
            }
            Ok(())
        }
        VehicleCommand::Directed(t) => {
            if kind == VehicleKind::Rover {
                return Err(format!(
                    "{cmd} with altitude, speed and bearing refused: a rover has no such \
                     DIRECTED (its DIRECTED is the RC pilot driving); use change_state"
                ));
            }
            if from != Directed {
                check(kind, from, Directed)
                    .map_err(|why| format!("{cmd} refused in {from}: {why}"))?;
            }
            check_directed(t).map_err(|why| format!("{cmd} refused: {why}"))
        }
    }
}

/// Whether a DIRECTED target can be flown.
fn check_directed(t: &DirectedTarget) -> Result<(), String> {
    if !(t.alt.is_finite() && t.alt >= 2.0) {
        return Err(format!(
            "altitude {} m above home is not at least 2 m",
            t.alt
        ));
    }
    if !(t.speed.is_finite() && t.speed > 0.0) {
        return Err(format!("speed {} m/s is not positive", t.speed));
    }
    if !(t.bearing.is_finite() && (0.0..=360.0).contains(&t.bearing)) {
        return Err(format!("bearing {} is not in 0..360 degrees", t.bearing));
    }
    Ok(())
}

/// The commands accepted from `from` with the motors `armed`.
pub fn allowed_commands(kind: VehicleKind, from: FlightState, armed: bool) -> Vec<&'static str> {
    let probe = [
        VehicleCommand::Arm,
        VehicleCommand::Disarm,
        VehicleCommand::Directed(DirectedTarget {
            alt: 10.0,
            speed: 1.0,
            bearing: 0.0,
        }),
    ];
    probe
        .iter()
        .filter(|c| check_command(kind, from, armed, c).is_ok())
        .map(VehicleCommand::name)
        .collect()
}

/// Everything a station may offer from `from` (variable `allowed_changes`).
pub fn allowed_changes(kind: VehicleKind, from: FlightState, armed: bool) -> AllowedChanges {
    AllowedChanges {
        from: Some(from),
        kind,
        states: allowed(kind, from),
        commands: allowed_commands(kind, from, armed)
            .into_iter()
            .map(str::to_owned)
            .collect(),
        armed,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_states_of_the_vehicle_are_allowed() {
        for kind in [VehicleKind::Rover, VehicleKind::Copter, VehicleKind::Plane] {
            for from in FlightState::ALL.into_iter().filter(|s| s.applies_to(kind)) {
                let to = allowed(kind, from);
                assert!(
                    to.iter().all(|s| s.applies_to(kind) && *s != from),
                    "{kind} {from}"
                );
            }
        }
        // A plane on the ground taxis; a copter has no TAXI.
        assert!(allowed(VehicleKind::Plane, Parking).contains(&Taxi));
        assert!(!allowed(VehicleKind::Copter, Parking).contains(&Taxi));
        assert_eq!(
            allowed(VehicleKind::Plane, Taxi),
            [Parking, TakeOff, Manual]
        );
        let e = check(VehicleKind::Copter, Parking, Taxi).unwrap_err();
        assert_eq!(e, "TAXI is not a state of a copter");
        let e = check(VehicleKind::Plane, Taxi, WaypointNavigation).unwrap_err();
        assert!(e.contains("allowed: PARKING, TAKE_OFF, MANUAL"), "{e}");
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

    #[test]
    fn every_kind_returns_to_launch_and_aircraft_take_off_and_land() {
        for kind in [VehicleKind::Rover, VehicleKind::Copter, VehicleKind::Plane] {
            assert_eq!(check(kind, WaypointNavigation, ReturnToLaunch), Ok(()));
            assert_eq!(check(kind, Directed, ReturnToLaunch), Ok(()));
        }
        for kind in [VehicleKind::Copter, VehicleKind::Plane] {
            assert_eq!(check(kind, Parking, TakeOff), Ok(()));
            assert_eq!(check(kind, WaypointNavigation, Landing), Ok(()));
            assert_eq!(check(kind, ReturnToLaunch, Landing), Ok(()));
        }
        assert_eq!(check(VehicleKind::Rover, ReturnToLaunch, Parking), Ok(()));
    }

    #[test]
    fn arm_and_disarm_only_parked_and_only_when_they_change_something() {
        let (r, c) = (VehicleKind::Rover, VehicleKind::Copter);
        assert_eq!(
            check_command(r, Parking, false, &VehicleCommand::Arm),
            Ok(())
        );
        assert_eq!(
            check_command(r, Directed, true, &VehicleCommand::Disarm),
            Ok(())
        );
        assert_eq!(
            check_command(c, Parking, true, &VehicleCommand::Disarm),
            Ok(())
        );
        let e = check_command(c, WaypointNavigation, true, &VehicleCommand::Disarm).unwrap_err();
        assert!(
            e.contains("DISARM") && e.contains("WAYPOINT_NAVIGATION") && e.contains("PARKING"),
            "{e}"
        );
        let e = check_command(c, Directed, true, &VehicleCommand::Disarm).unwrap_err();
        assert!(e.contains("DIRECTED"), "{e}");
        let e = check_command(r, Parking, true, &VehicleCommand::Arm).unwrap_err();
        assert!(e.contains("already armed"), "{e}");
        let e = check_command(r, Manual, false, &VehicleCommand::Arm).unwrap_err();
        assert!(e.contains("failsafe"), "{e}");
        assert_eq!(allowed_commands(r, Parking, false), ["ARM"]);
        assert_eq!(allowed_commands(c, Parking, true), ["DISARM"]);
        let e = check_command(c, Parking, false, &VehicleCommand::Arm).unwrap_err();
        assert!(e.contains("TAKE_OFF"), "{e}");
        let p = VehicleKind::Plane;
        assert_eq!(allowed_commands(p, Parking, false), ["ARM"]);
        assert!(allowed_commands(r, WaypointNavigation, true).is_empty());
    }

    #[test]
    fn directed_flight_is_for_airborne_aircraft_with_a_sane_target() {
        let t = DirectedTarget {
            alt: 30.0,
            speed: 5.0,
            bearing: 90.0,
        };
        let d = VehicleCommand::Directed(t);
        let c = VehicleKind::Copter;
        assert_eq!(check_command(c, WaypointNavigation, true, &d), Ok(()));
        assert_eq!(check_command(c, Directed, true, &d), Ok(()));
        assert_eq!(check_command(VehicleKind::Plane, TakeOff, true, &d), Ok(()));
        let e = check_command(c, Parking, false, &d).unwrap_err();
        assert!(e.contains("PARKING") && e.contains("TAKE_OFF"), "{e}");
        let e = check_command(VehicleKind::Rover, Parking, true, &d).unwrap_err();
        assert!(e.contains("rover"), "{e}");
        for bad in [
            DirectedTarget { alt: 0.5, ..t },
            DirectedTarget { speed: 0.0, ..t },
            DirectedTarget {
                bearing: f32::NAN,
                ..t
            },
            DirectedTarget {
                alt: f64::INFINITY,
                ..t
            },
        ] {
            assert!(check_command(c, Directed, true, &VehicleCommand::Directed(bad)).is_err());
        }
        let a = allowed_changes(c, WaypointNavigation, true);
        assert_eq!(a.commands, ["DIRECTED"]);
        assert!(a.states.contains(&ReturnToLaunch));
    }
}
