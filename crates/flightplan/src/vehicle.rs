//! Vehicle parameters that shape the waypoint stream (003 §6.2.3: a rover needs waypoints 4-5 m
//! apart where an aircraft uses 100 m).

use serde::{Deserialize, Serialize};

/// What kind of vehicle a plan is expanded for.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum VehicleKind {
    /// A ground rover that can turn on the spot.
    Rover,
    /// A fixed-wing aircraft.
    Aircraft,
    /// A multirotor: hovers, turns where it stands, climbs and lands vertically.
    Copter,
}

impl VehicleKind {
    /// The name used in plans and config files.
    pub fn name(self) -> &'static str {
        match self {
            VehicleKind::Rover => "rover",
            VehicleKind::Aircraft => "aircraft",
            VehicleKind::Copter => "copter",
        }
    }
    /// Every kind, in the order plans and config files list them.
    pub const ALL: [VehicleKind; 3] = [
        VehicleKind::Rover,
        VehicleKind::Aircraft,
        VehicleKind::Copter,
    ];
    /// The names of every kind, for an error message: "`rover`, `aircraft` or `copter`".
    pub fn choices() -> String {
        "`rover`, `aircraft` or `copter`".to_owned()
    }
    /// The kind named `s` (`rover`, `aircraft`, `copter`).
    pub fn from_name(s: &str) -> Option<Self> {
        Self::ALL.into_iter().find(|k| k.name() == s)
    }
}

impl std::fmt::Display for VehicleKind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// Parameters of the vehicle a plan is flown by.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct VehicleParams {
    /// Kind.
    pub kind: VehicleKind,
    /// Minimum distance between consecutive waypoints, metres: closer ones are dropped.
    pub min_wp_distance: f64,
    /// Speed when neither the leg nor the plan gives one, m/s.
    pub default_speed: f64,
    /// Minimum turn radius, metres: scans need spacing ≥ 2 × this, racetrack holds width ≥ 2 × this.
    pub turn_radius: f64,
    /// Largest angle between two waypoints of a densified arc, degrees.
    pub max_arc_step_deg: f64,
    /// Length of the inbound course drawn for a CF leg when the leg does not give one, metres.
    pub cf_length: f64,
}

impl VehicleParams {
    /// A small rover (the car-park tests of 003 §6.1.2).
    pub fn rover() -> Self {
        Self {
            kind: VehicleKind::Rover,
            min_wp_distance: 4.5,
            default_speed: 2.0,
            turn_radius: 1.0,
            max_arc_step_deg: 45.0,
            cf_length: 20.0,
        }
    }
    /// A small fixed-wing aircraft.
    pub fn aircraft() -> Self {
        Self {
            kind: VehicleKind::Aircraft,
            min_wp_distance: 100.0,
            default_speed: 22.0,
            turn_radius: 60.0,
            max_arc_step_deg: 45.0,
            cf_length: 1000.0,
        }
    }
    /// A small multirotor (the MAUVET and EAMOS quadcopters): waypoints a few metres apart,
    /// turns on the spot, 5 m/s cruise.
    pub fn copter() -> Self {
        Self {
            kind: VehicleKind::Copter,
            min_wp_distance: 3.0,
            default_speed: 5.0,
            turn_radius: 1.0,
            max_arc_step_deg: 30.0,
            cf_length: 100.0,
        }
    }
    /// The longest track between two consecutive waypoints a plan for this vehicle may have,
    /// metres: a sanity bound that catches a coordinate typed wrong before the plan flies (a
    /// small rover's battery does not reach 50 km, a small multirotor's not 20 km, a small
    /// aircraft's not 500 km).
    pub fn longest_leg_m(&self) -> f64 {
        match self.kind {
            VehicleKind::Rover => 50_000.0,
            VehicleKind::Aircraft => 500_000.0,
            VehicleKind::Copter => 20_000.0,
        }
    }

    /// How far from home a waypoint may lie before the launcher warns that a coordinate may be
    /// typed wrong, metres (a warning, not a refusal: a long survey is a choice).
    pub fn far_from_home_m(&self) -> f64 {
        match self.kind {
            VehicleKind::Rover | VehicleKind::Copter => 5_000.0,
            VehicleKind::Aircraft => 50_000.0,
        }
    }

    /// The defaults for `kind`.
    pub fn for_kind(kind: VehicleKind) -> Self {
        match kind {
            VehicleKind::Rover => Self::rover(),
            VehicleKind::Aircraft => Self::aircraft(),
            VehicleKind::Copter => Self::copter(),
        }
    }
}
