//! The catalogue of the FPMa's items (the `fpma` service: `<namespace>/fpma/<item>`): each
//! item's name together with its type, as a `marea` typed handle, for the service that provides
//! them and the stations and tools that follow and call them. The names on the wire are the
//! strings below; `services/fpma/README.md` says what each carries and when. (The `plans` file
//! sink has no payload type, so no handle.)
//!
//! ```
//! use flightplan::api::items as fpma;
//! assert_eq!(fpma::PROGRESS.at("rover1/fpma"), "rover1/fpma/progress");
//! assert_eq!(fpma::LOAD_PLAN.at("**/fpma"), "**/fpma/load_plan");
//! ```

use marea::{EventItem, FunctionItem, VariableItem};
use usal_types::CommandRecord;

use super::{
    CommandAck, HoldHereArgs, ModifyLeg, PlanEvent, PlanGeometry, PlanLoaded, PlanRejected,
    PlanState, Progress, Readiness, Retask, SetVar,
};

/// How far the plan has been flown, after every input.
pub const PROGRESS: VariableItem<Progress> = VariableItem::new("progress");
/// Plan variables, loop passes, sequence numbers queued at the VAS.
pub const STATE: VariableItem<PlanState> = VariableItem::new("state");
/// What a station draws: the legs and the nominal waypoints, per plan version.
pub const PLAN: VariableItem<PlanGeometry> = VariableItem::new("plan");
/// Whether the plan waits for the operator's start, else why not.
pub const READY: VariableItem<Readiness> = VariableItem::new("ready");

/// What happened in the plan: loaded, legs started and completed, stages, emergencies.
pub const PLAN_EVENT: EventItem<PlanEvent> = EventItem::new("plan_event");
/// A plan file that did not load, and why.
pub const PLAN_REJECTED: EventItem<PlanRejected> = EventItem::new("plan_rejected");
/// A command or plan load received, who sent it and the answer.
pub const COMMANDS: EventItem<CommandRecord> = EventItem::new("commands");

/// Loads a plan (its XML), replacing the current one.
pub const LOAD_PLAN: FunctionItem<String, PlanLoaded> = FunctionItem::new("load_plan");
/// As [`LOAD_PLAN`], refused when no plan is loaded.
pub const REPLACE_PLAN: FunctionItem<String, PlanLoaded> = FunctionItem::new("replace_plan");
/// The [`PLAN`] variable's value on request.
pub const PLAN_GEOMETRY: FunctionItem<(), PlanGeometry> = FunctionItem::new("plan_geometry");
/// The [`PROGRESS`] variable's last value on request (the same name as the variable).
pub const LAST_PROGRESS: FunctionItem<(), Progress> = FunctionItem::new("progress");
/// Ends the current leg.
pub const SKIP_LEG: FunctionItem<(), CommandAck> = FunctionItem::new("skip_leg");
/// Enters a leg, loop or alternative (its id) afresh.
pub const GOTO_LEG: FunctionItem<String, CommandAck> = FunctionItem::new("goto_leg");
/// Goes to a stage (`takeoff`, `departure`, `mission`, `approach`, `landing`).
pub const GOTO_STAGE: FunctionItem<String, CommandAck> = FunctionItem::new("goto_stage");
/// Sets a plan variable.
pub const SET_VAR: FunctionItem<SetVar, CommandAck> = FunctionItem::new("set_var");
/// Holds where the vehicle is.
pub const HOLD_HERE: FunctionItem<HoldHereArgs, CommandAck> = FunctionItem::new("hold_here");
/// Leaves the hold: at once (`true`) or at the next fix crossing.
pub const EXIT_HOLD: FunctionItem<bool, CommandAck> = FunctionItem::new("exit_hold");
/// Lets the VAS queue run out after its target.
pub const PAUSE: FunctionItem<(), CommandAck> = FunctionItem::new("pause");
/// Refills the VAS queue after a pause.
pub const RESUME: FunctionItem<(), CommandAck> = FunctionItem::new("resume");
/// Changes a leg's parameters (a new version).
pub const MODIFY_LEG: FunctionItem<ModifyLeg, CommandAck> = FunctionItem::new("modify_leg");
/// Re-tasks the vehicle to points.
pub const RETASK: FunctionItem<Retask, CommandAck> = FunctionItem::new("retask");
/// Inserts legs (the plan's XML) after the current leg.
pub const INSERT_LEGS: FunctionItem<String, CommandAck> = FunctionItem::new("insert_legs");
/// Fires an emergency rule (none: the default reaction).
pub const EMERGENCY: FunctionItem<Option<String>, CommandAck> = FunctionItem::new("emergency");
