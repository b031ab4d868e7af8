//! What goes in and out of the executive: why a command was refused, the events it emits, the
//! arguments of its commands, the telemetry it reads and the snapshot it gives stations.

use crate::expr::Value;
use crate::geo::GeoPoint;
use crate::model::*;
use crate::parse::PlanError;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use thiserror::Error;

/// Why a command or report was refused. The executive is unchanged when one is returned.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum CommandError {
    /// The new or modified plan does not validate.
    #[error("invalid plan: {0}")]
    InvalidPlan(#[from] PlanError),
    /// No node has this id.
    #[error("unknown leg `{0}`")]
    UnknownLeg(String),
    /// The plan has no nodes in this stage.
    #[error("the plan has no {0} stage")]
    EmptyStage(Stage),
    /// Neither declared nor a settable built-in.
    #[error("unknown variable `{0}`")]
    UnknownVariable(String),
    /// Value of the wrong type.
    #[error("variable `{name}` is a {expected}")]
    TypeMismatch {
        /// Variable.
        name: String,
        /// Its type.
        expected: crate::expr::ValueType,
    },
    /// The changed plan's nominal expansion would not end (a huge count, circuit number...).
    #[error("{0}")]
    Endless(#[from] ExpandError),
    /// Nothing is being flown.
    #[error("the plan is completed: nothing to skip")]
    NothingToSkip,
    /// `exit_hold` while not holding.
    #[error("the current leg is not a hold")]
    NotHolding,
    /// `pause` twice.
    #[error("already paused")]
    AlreadyPaused,
    /// `resume` while running.
    #[error("not paused")]
    NotPaused,
    /// The command needs a position and none is known yet.
    #[error("no present position is known yet")]
    NoPosition,
    /// A report for another plan version.
    #[error("waypoint of plan version {got}, the current version is {current}")]
    StaleVersion {
        /// Reported.
        got: u64,
        /// Current.
        current: u64,
    },
    /// A report for a waypoint already passed.
    #[error("waypoint {seq} was already reached (next is {next})")]
    AlreadyReached {
        /// Reported.
        seq: u64,
        /// Next expected.
        next: u64,
    },
    /// A report for a waypoint the stream does not reach.
    #[error("waypoint {0} is beyond the end of the plan")]
    BeyondPlan(u64),
    /// No emergency rule has this name.
    #[error("unknown emergency rule `{0}`")]
    UnknownRule(String),
    /// Re-task with no points.
    #[error("re-task needs at least one point")]
    NoPoints,
    /// A command argument out of range (a NaN, a negative length, a latitude of 91...).
    #[error("{what}: {why}")]
    BadArgument {
        /// The argument.
        what: String,
        /// What is expected.
        why: String,
    },
}

pub(super) fn bad_arg(what: impl Into<String>, why: &str) -> CommandError {
    CommandError::BadArgument {
        what: what.into(),
        why: why.into(),
    }
}

pub(super) fn check_point(what: &str, p: GeoPoint) -> Result<(), CommandError> {
    if !(p.lat.is_finite() && (-90.0..=90.0).contains(&p.lat)) {
        return Err(bad_arg(
            what,
            &format!("latitude {} is not in -90..90", p.lat),
        ));
    }
    if !(p.lon.is_finite() && (-180.0..=180.0).contains(&p.lon)) {
        return Err(bad_arg(
            what,
            &format!("longitude {} is not in -180..180", p.lon),
        ));
    }
    Ok(())
}

/// An event for stations, tagged with the plan version it belongs to.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Event {
    /// Plan version.
    pub version: u64,
    /// What happened.
    pub kind: EventKind,
}

/// Declares an enum of the flight events (legs, waypoints, loops, branches, stages, in-place
/// changes, emergencies, pause) with variants of its own before and after them, and the integer
/// type of a branch index.
///
/// Why a macro: the executive's [`EventKind`] (JSON, internally tagged by name, with progress
/// and replacement notices) and the wire's [`crate::api::PlanEventKind`] (postcard, tagged by
/// position, so its variants' order is its encoding; a `u32` branch) carry the same events but
/// must keep their own encodings; one list of variants serves both.
macro_rules! flight_events {
    (
        $(#[$meta:meta])*
        $vis:vis enum $name:ident (branch: $branch:ty) {
            $($first:tt)*
        }
        then {
            $($last:tt)*
        }
    ) => {
        $(#[$meta])*
        $vis enum $name {
            $($first)*
            /// A leg became the current one.
            LegStarted {
                /// Leg id.
                leg: String,
            },
            /// A leg ended (`skipped` when by command).
            LegCompleted {
                /// Leg id.
                leg: String,
                /// Ended by a command rather than flown to its end.
                skipped: bool,
            },
            /// A waypoint was reached.
            WaypointReached {
                /// Its sequence number.
                seq: u64,
                /// Its leg.
                leg: String,
            },
            /// A loop finished pass `n` (from 1).
            IterationDone {
                /// Loop id.
                leg: String,
                /// Passes done.
                n: u32,
            },
            /// An alternative chose a branch (0-based; `otherwise` is the last).
            BranchTaken {
                /// Alternative id.
                leg: String,
                /// Branch index.
                branch: $branch,
            },
            /// A new stage began.
            StageChanged {
                /// The stage.
                stage: Stage,
            },
            /// Nothing is left to fly.
            PlanCompleted,
            /// The plan was changed in place (modified or inserted legs).
            PlanModified {
                /// The leg changed or the first inserted.
                leg: String,
            },
            /// An emergency rule fired or the command was given.
            EmergencyFired {
                /// Rule name (`default` for the command without one).
                rule: String,
            },
            /// Paused.
            Paused,
            /// Resumed.
            Resumed,
            $($last)*
        }
    };
}
pub(crate) use flight_events;

flight_events! {
    /// What happened.
    #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
    #[serde(tag = "event", rename_all = "kebab-case")]
    pub enum EventKind (branch: usize) {}
    then {
        /// Progress by distance (seed 000): flown / (flown + remaining planned).
        Progress {
            /// In [0, 1].
            fraction: f64,
            /// Metres flown in this plan version.
            flown_m: f64,
            /// Metres left in the nominal continuation.
            remaining_m: f64,
        },
        /// A new plan replaced the old one.
        PlanReplaced,
    }
}

/// Dimensions of a hold commanded in flight at the present position.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct HoldHere {
    /// Straight-leg length, metres (default 5 × minimum waypoint distance).
    pub length: Option<f64>,
    /// Width, metres (default as for plan holds).
    pub width: Option<f64>,
    /// Turn direction.
    pub turn: Turn,
    /// Inbound course; default the present track.
    pub inbound_course: Option<f64>,
    /// Shape; default rectangle for a rover, racetrack otherwise.
    pub shape: Option<HoldShape>,
}

impl Default for HoldHere {
    fn default() -> Self {
        Self {
            length: None,
            width: None,
            turn: Turn::R,
            inbound_course: None,
            shape: None,
        }
    }
}

/// When re-tasked points are visited.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum RetaskMode {
    /// Interrupt the current leg, visit the points, then resume the leg where it was.
    Now,
    /// Insert the points as TF legs after the current leg (a new plan version).
    AfterCurrentLeg,
}

/// Telemetry the executive reads for built-in variables and the present position.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Telemetry {
    /// Present position.
    pub position: Option<GeoPoint>,
    /// Altitude (`alt`).
    pub alt: Option<f64>,
    /// Ground speed (`ground_speed`).
    pub ground_speed: Option<f64>,
    /// Battery (`battery`), percent.
    pub battery: Option<f64>,
    /// Seconds since start (`elapsed_s`).
    pub elapsed_s: Option<f64>,
}

/// A snapshot of the executive for stations.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExecState {
    /// Plan version.
    pub version: u64,
    /// Plan name.
    pub plan: String,
    /// Current stage.
    pub stage: Option<Stage>,
    /// Current leg id.
    pub leg: Option<String>,
    /// Sequence number of the next waypoint.
    pub next_seq: u64,
    /// Paused.
    pub paused: bool,
    /// Completed.
    pub completed: bool,
    /// The current leg is a hold.
    pub holding: bool,
    /// Enclosing loops: (id, passes done).
    pub loops: Vec<(String, u32)>,
    /// Variables.
    pub vars: BTreeMap<String, Value>,
}

/// Why a nominal expansion failed.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum ExpandError {
    /// The plan did not end within the step limit.
    #[error("the plan produces more than {0} waypoints without ending")]
    Endless(usize),
}
