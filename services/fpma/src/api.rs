//! The `fpma` service's wire types: the arguments and results of its functions and the values of
//! its variables and events, shared by the service and the ground stations (FPMo, `usal call`).
//!
//! The middleware encodes payloads with postcard, which is not self-describing: every type here
//! is a plain struct or an externally tagged enum (no `untagged`, no internally tagged enums, no
//! skipped fields), unlike the library's own JSON-oriented types, which are converted here.

use serde::{Deserialize, Serialize};

use crate::exec::{Event, EventKind, HoldHere, RetaskMode};
use crate::expr::Value;
use crate::model::Stage;

/// A plan variable's value.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub enum VarValue {
    /// A boolean.
    Bool(bool),
    /// A number.
    Number(f64),
}

impl From<Value> for VarValue {
    fn from(v: Value) -> Self {
        match v {
            Value::Bool(b) => VarValue::Bool(b),
            Value::Number(n) => VarValue::Number(n),
        }
    }
}

impl From<VarValue> for Value {
    fn from(v: VarValue) -> Self {
        match v {
            VarValue::Bool(b) => Value::Bool(b),
            VarValue::Number(n) => Value::Number(n),
        }
    }
}

/// Result of `load_plan`, `replace_plan` and of a plan file accepted by the `plans` sink.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlanLoaded {
    /// The version the plan is flown as.
    pub version: u64,
    /// The plan's name.
    pub name: String,
    /// Waypoints handed to the VAS so far.
    pub queued: u64,
    /// Why the VAS refused WAYPOINT_NAVIGATION, when it was asked and refused (the plan is loaded
    /// all the same and flies once the vehicle is put in that state).
    pub navigation_refused: Option<String>,
}

/// A plan file that arrived on the `plans` sink and was not loaded (event `plan_rejected`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlanRejected {
    /// The file name as sent.
    pub file: String,
    /// The sending node.
    pub from: String,
    /// Why, e.g. `carpark.xml:12:7: unknown fix `P9``.
    pub reason: String,
}

/// Result of every in-flight command.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CommandAck {
    /// The plan version after the command.
    pub version: u64,
    /// The current leg after the command.
    pub leg: Option<String>,
    /// Sequence number of the next waypoint.
    pub next_seq: u64,
}

/// Arguments of `modify_leg`: attribute changes as they would be written in the XML.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ModifyLeg {
    /// The leg (or scan, hold...) id.
    pub leg: String,
    /// `(attribute, value)` pairs, e.g. `("spacing", "10")`.
    pub changes: Vec<(String, String)>,
}

/// Arguments of `set_var`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct SetVar {
    /// Variable name (declared in the plan, or `battery`, `alt`, `ground_speed`, `elapsed_s`).
    pub name: String,
    /// New value.
    pub value: VarValue,
}

/// Turn direction of a commanded hold.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum HoldTurn {
    /// Right.
    #[default]
    Right,
    /// Left.
    Left,
}

/// Shape of a commanded hold.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum HoldShapeArg {
    /// Straight legs joined by semicircles.
    Racetrack,
    /// Four fly-over corners (a rover).
    Rectangle,
}

/// Arguments of `hold_here` (every field optional: the defaults of [`HoldHere`]).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct HoldHereArgs {
    /// Straight-leg length, metres.
    pub length: Option<f64>,
    /// Width, metres.
    pub width: Option<f64>,
    /// Turn direction.
    pub turn: HoldTurn,
    /// Inbound course, degrees; default the present track.
    pub inbound_course: Option<f64>,
    /// Shape; default rectangle for a rover, racetrack otherwise.
    pub shape: Option<HoldShapeArg>,
}

impl From<&HoldHereArgs> for HoldHere {
    fn from(a: &HoldHereArgs) -> Self {
        use crate::model::{HoldShape, Turn};
        HoldHere {
            length: a.length,
            width: a.width,
            turn: match a.turn {
                HoldTurn::Right => Turn::R,
                HoldTurn::Left => Turn::L,
            },
            inbound_course: a.inbound_course,
            shape: a.shape.map(|s| match s {
                HoldShapeArg::Racetrack => HoldShape::Racetrack,
                HoldShapeArg::Rectangle => HoldShape::Rectangle,
            }),
        }
    }
}

/// When re-tasked points are visited.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub enum RetaskWhen {
    /// Interrupt the current leg, visit the points, resume the leg.
    #[default]
    Now,
    /// After the current leg (a new plan version).
    AfterCurrentLeg,
}

impl From<RetaskWhen> for RetaskMode {
    fn from(w: RetaskWhen) -> Self {
        match w {
            RetaskWhen::Now => RetaskMode::Now,
            RetaskWhen::AfterCurrentLeg => RetaskMode::AfterCurrentLeg,
        }
    }
}

/// Arguments of `retask`: points of interest, visited in nearest-neighbour order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Retask {
    /// `(lat, lon)` in degrees.
    pub points: Vec<(f64, f64)>,
    /// Altitude; default the present one.
    pub alt: Option<f64>,
    /// When.
    pub when: RetaskWhen,
}

/// Progress of the plan (variable `progress`), by distance as seed 000 measures it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Progress {
    /// Plan version (0 before any plan).
    pub version: u64,
    /// Plan name.
    pub plan: String,
    /// Current stage.
    pub stage: Option<Stage>,
    /// Current leg.
    pub leg: Option<String>,
    /// Last waypoint reached (sequence number).
    pub last_reached: Option<u64>,
    /// Sequence number of the next waypoint.
    pub next_seq: u64,
    /// Metres flown in this plan version.
    pub flown_m: f64,
    /// Metres planned: flown plus the nominal rest.
    pub planned_m: f64,
    /// `flown / planned` in [0, 1]; 1 when completed.
    pub fraction: f64,
    /// Paused by command.
    pub paused: bool,
    /// Nothing left to fly.
    pub completed: bool,
    /// The current leg is a hold.
    pub holding: bool,
}

/// The executive's variables and loops (variable `state`), for stations.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PlanState {
    /// Plan version (0 before any plan).
    pub version: u64,
    /// Enclosing loops of the current leg: `(id, passes done)`.
    pub loops: Vec<(String, u32)>,
    /// Plan variables and built-ins.
    pub vars: Vec<(String, VarValue)>,
    /// Sequence numbers handed to the VAS and not reached yet.
    pub queued: Vec<u64>,
}

/// One event of the executive (event `plan_event`), tagged with the plan version.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PlanEvent {
    /// Plan version.
    pub version: u64,
    /// What happened.
    pub kind: PlanEventKind,
}

/// What happened (the executive's events; progress is the `progress` variable instead).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum PlanEventKind {
    /// A plan was loaded (the first one, or one replacing the previous).
    PlanLoaded {
        /// Its name.
        name: String,
    },
    /// A leg became the current one.
    LegStarted {
        /// Leg id.
        leg: String,
    },
    /// A leg ended.
    LegCompleted {
        /// Leg id.
        leg: String,
        /// Ended by a command.
        skipped: bool,
    },
    /// A waypoint was reached.
    WaypointReached {
        /// Sequence number.
        seq: u64,
        /// Its leg.
        leg: String,
    },
    /// A loop finished pass `n`.
    IterationDone {
        /// Loop id.
        leg: String,
        /// Passes done.
        n: u32,
    },
    /// An alternative chose a branch (0-based; `otherwise` last).
    BranchTaken {
        /// Alternative id.
        leg: String,
        /// Branch index.
        branch: u32,
    },
    /// A new stage began.
    StageChanged {
        /// The stage.
        stage: Stage,
    },
    /// Nothing is left to fly.
    PlanCompleted,
    /// The plan was changed in place (a modified leg, inserted legs).
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
}

impl PlanEvent {
    /// The wire form of an executive event; `None` for progress (published as a variable) and
    /// for the replacement notice (the service raises [`PlanEventKind::PlanLoaded`] instead).
    pub fn from_exec(e: Event) -> Option<PlanEvent> {
        let kind = match e.kind {
            EventKind::LegStarted { leg } => PlanEventKind::LegStarted { leg },
            EventKind::LegCompleted { leg, skipped } => {
                PlanEventKind::LegCompleted { leg, skipped }
            }
            EventKind::WaypointReached { seq, leg } => PlanEventKind::WaypointReached { seq, leg },
            EventKind::IterationDone { leg, n } => PlanEventKind::IterationDone { leg, n },
            EventKind::BranchTaken { leg, branch } => PlanEventKind::BranchTaken {
                leg,
                branch: u32::try_from(branch).unwrap_or(u32::MAX),
            },
            EventKind::StageChanged { stage } => PlanEventKind::StageChanged { stage },
            EventKind::PlanCompleted => PlanEventKind::PlanCompleted,
            EventKind::PlanModified { leg } => PlanEventKind::PlanModified { leg },
            EventKind::EmergencyFired { rule } => PlanEventKind::EmergencyFired { rule },
            EventKind::Paused => PlanEventKind::Paused,
            EventKind::Resumed => PlanEventKind::Resumed,
            EventKind::Progress { .. } | EventKind::PlanReplaced => return None,
        };
        Some(PlanEvent {
            version: e.version,
            kind,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every wire type survives postcard, which refuses self-describing serde features.
    #[test]
    fn wire_types_round_trip_through_postcard() {
        fn rt<T: Serialize + for<'de> Deserialize<'de> + PartialEq + std::fmt::Debug>(v: T) {
            let bytes = postcard::to_stdvec(&v).expect("encodes");
            let back: T = postcard::from_bytes(&bytes).expect("decodes");
            assert_eq!(back, v);
        }
        rt(PlanEvent {
            version: 3,
            kind: PlanEventKind::StageChanged {
                stage: Stage::Approach,
            },
        });
        rt(PlanEvent {
            version: 1,
            kind: PlanEventKind::LegCompleted {
                leg: "area".into(),
                skipped: true,
            },
        });
        rt(Progress {
            version: 2,
            plan: "p".into(),
            stage: Some(Stage::Mission),
            leg: Some("hold".into()),
            last_reached: Some(7),
            next_seq: 8,
            flown_m: 12.5,
            planned_m: 100.0,
            fraction: 0.125,
            ..Progress::default()
        });
        rt(PlanState {
            version: 1,
            loops: vec![("laps".into(), 1)],
            vars: vec![
                ("inspect".into(), VarValue::Bool(true)),
                ("laps".into(), VarValue::Number(2.0)),
            ],
            queued: vec![8, 9],
        });
        rt(SetVar {
            name: "inspect".into(),
            value: VarValue::Bool(true),
        });
        rt(ModifyLeg {
            leg: "area".into(),
            changes: vec![("spacing".into(), "10".into())],
        });
        rt(HoldHereArgs {
            length: Some(20.0),
            shape: Some(HoldShapeArg::Rectangle),
            ..HoldHereArgs::default()
        });
        rt(Retask {
            points: vec![(41.0, 2.0)],
            alt: None,
            when: RetaskWhen::AfterCurrentLeg,
        });
        rt(PlanLoaded {
            version: 1,
            name: "p".into(),
            queued: 8,
            navigation_refused: Some("no".into()),
        });
        rt(CommandAck {
            version: 1,
            leg: None,
            next_seq: 0,
        });
        rt(PlanRejected {
            file: "a.xml".into(),
            from: "gcs".into(),
            reason: "3:1: x".into(),
        });
    }
}
