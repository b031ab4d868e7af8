//! The catalogue of the fleet service's items (`<namespace>/fleet/<item>`): each item's name
//! together with its type, as a `marea` typed handle, for the service and the stations and
//! tools that follow it. `services/fleet/README.md` says what each carries.
//!
//! ```
//! use flightplan::fleet_api::items as fleet;
//! assert_eq!(fleet::STATUS.at("**/fleet"), "**/fleet/status");
//! ```

use marea::{FunctionItem, VariableItem};

use super::{FleetStatus, PointEdit};

/// The fleet plan's state: vehicles, detections, separation, variables.
pub const STATUS: VariableItem<FleetStatus> = VariableItem::new("status");
/// Holds a vehicle (its id in the fleet plan) where it is until [`RESUME`]; answers in words.
pub const PAUSE: FunctionItem<String, String> = FunctionItem::new("pause");
/// Lets a paused vehicle (its id) go on; answers in words.
pub const RESUME: FunctionItem<String, String> = FunctionItem::new("resume");
/// An operator's change to the points the investigators visit: add, delete, put first;
/// answers in words, or refuses saying why (a point inside an obstacle, an unknown one).
pub const EDIT_POINTS: FunctionItem<PointEdit, String> = FunctionItem::new("edit_points");
