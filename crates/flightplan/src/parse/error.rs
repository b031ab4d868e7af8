//! Plan errors: what is wrong with a plan and the line and column where.

use crate::expr::ExprError;
use crate::vehicle::VehicleKind;
use crate::xml::{Pos, XmlError};
use thiserror::Error;

/// A plan that cannot be loaded, with the position of the problem.
#[derive(Debug, Clone, PartialEq, Error)]
#[error("{line}:{col}: {kind}")]
pub struct PlanError {
    /// 1-based line (0 for nodes built in code).
    pub line: u32,
    /// 1-based column.
    pub col: u32,
    /// What is wrong.
    pub kind: PlanErrorKind,
}

/// What is wrong with a plan.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum PlanErrorKind {
    /// Not well-formed XML.
    #[error("{0}")]
    Xml(String),
    /// An element the format does not have here.
    #[error("unknown element <{name}> in <{parent}>")]
    UnknownElement {
        /// The element.
        name: String,
        /// Where it was found.
        parent: String,
    },
    /// An attribute the element does not have.
    #[error("unknown attribute `{name}` on <{element}>")]
    UnknownAttribute {
        /// The attribute.
        name: String,
        /// The element.
        element: String,
    },
    /// A required attribute is absent.
    #[error("<{element}> needs attribute `{name}`")]
    MissingAttribute {
        /// The attribute.
        name: String,
        /// The element.
        element: String,
    },
    /// A number that does not parse or is not finite.
    #[error("attribute `{name}`: `{value}` is not a number")]
    BadNumber {
        /// The attribute.
        name: String,
        /// Its text.
        value: String,
    },
    /// A value outside what the attribute accepts.
    #[error("attribute `{name}`: `{value}` {why}")]
    BadValue {
        /// The attribute.
        name: String,
        /// Its text.
        value: String,
        /// What is expected.
        why: String,
    },
    /// A leg refers to a fix that is not declared.
    #[error("unknown fix `{0}`")]
    UnknownFix(String),
    /// Two fixes with one id.
    #[error("fix `{0}` is declared twice")]
    DuplicateFix(String),
    /// Two nodes with one id.
    #[error("id `{0}` is used twice")]
    DuplicateId(String),
    /// Two variables with one name.
    #[error("variable `{0}` is declared twice (or shadows a built-in)")]
    DuplicateVariable(String),
    /// A polygon whose edges cross.
    #[error("the polygon self-intersects: edge {0} crosses edge {1} (edges numbered from 1)")]
    SelfIntersecting(usize, usize),
    /// A polygon with fewer than 3 vertices.
    #[error("a polygon needs at least 3 <pt> vertices, this one has {0}")]
    TooFewVertices(usize),
    /// Track spacing the vehicle cannot turn in.
    #[error(
        "spacing {spacing} m is below the vehicle's turn limit of {min} m (twice its turn radius)"
    )]
    SpacingBelowTurnLimit {
        /// Given spacing.
        spacing: f64,
        /// Smallest allowed.
        min: f64,
    },
    /// A dimension below the minimum waypoint distance.
    #[error("{what} {value} m is below the vehicle's minimum waypoint distance of {min} m")]
    BelowMinWaypointDistance {
        /// Which dimension.
        what: &'static str,
        /// Given value.
        value: f64,
        /// Smallest allowed.
        min: f64,
    },
    /// A racetrack narrower than the vehicle can turn.
    #[error(
        "hold width {width} m is below the vehicle's turn limit of {min} m (twice its turn radius)"
    )]
    HoldTooNarrow {
        /// Given width.
        width: f64,
        /// Smallest allowed.
        min: f64,
    },
    /// `count="0"`.
    #[error("iteration count must be at least 1")]
    ZeroIterations,
    /// A condition that does not parse or type-check.
    #[error(transparent)]
    Condition(#[from] ExprError),
    /// Misplaced, missing or repeated elements.
    #[error("{0}")]
    Structure(String),
    /// An emergency rule naming a leg that does not exist.
    #[error("unknown leg `{0}`")]
    UnknownLeg(String),
    /// The plan says it is for another kind of vehicle.
    #[error("the plan is written for vehicle `{plan}`, but this vehicle is `{vehicle}`")]
    WrongVehicle {
        /// The plan's `vehicle`.
        plan: VehicleKind,
        /// The vehicle it is loaded for.
        vehicle: VehicleKind,
    },
    /// A pattern bigger than the FPMa generates (the work and the memory grow with it).
    #[error("{what}: {value} is more than the {max} allowed")]
    TooLarge {
        /// What is counted.
        what: &'static str,
        /// How many the plan asks for.
        value: u64,
        /// The most allowed.
        max: u64,
    },
    /// A waypoint, or the track to it, outside the plan's `<fence>`.
    #[error("leg `{leg}` leaves the fence: {why}")]
    OutsideFence {
        /// The leg.
        leg: String,
        /// Which limit, where.
        why: String,
    },
    /// A leg far longer than the vehicle flies in one: most often a coordinate typed wrong (a
    /// negated latitude made a rover's leg 36,569 km).
    #[error(
        "leg `{leg}` is {km:.1} km long, more than a {vehicle} flies in one leg ({max_km:.0} km): \
         is a coordinate typed wrong?"
    )]
    LegTooLong {
        /// The leg.
        leg: String,
        /// Its length, km.
        km: f64,
        /// The longest a leg of this vehicle may be, km.
        max_km: f64,
        /// The vehicle.
        vehicle: crate::vehicle::VehicleKind,
    },
    /// The `<fence>` itself is unusable.
    #[error("fence: {0}")]
    BadFence(String),
}

impl PlanError {
    /// An error at `line`:`col` (for checks made after parsing, by node position).
    pub fn at_line(line: u32, col: u32, kind: PlanErrorKind) -> Self {
        Self { line, col, kind }
    }

    /// An error at `pos` (an element or an attribute).
    pub(crate) fn at(pos: Pos, kind: PlanErrorKind) -> Self {
        Self {
            line: pos.line,
            col: pos.col,
            kind,
        }
    }
}

impl From<XmlError> for PlanError {
    fn from(e: XmlError) -> Self {
        PlanError::at(e.pos, PlanErrorKind::Xml(e.message))
    }
}

pub(super) type Result<T> = std::result::Result<T, PlanError>;
