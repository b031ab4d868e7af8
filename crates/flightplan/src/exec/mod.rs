//! The executive (FLIGHTPLAN §3.6): a pure state machine that walks a plan with a cursor, keeps
//! the variables, hands out a short look-ahead of waypoints and advances on waypoint-reached
//! reports. No clock, no I/O: the service feeds it and publishes what it returns.
//!
//! The look-ahead is derived from the state each time it is asked for (a simulation on a copy),
//! so a plan has no waypoint limit and a variable set or a command given late still changes what
//! comes next. Every plan change bumps the plan version; waypoints and events carry it and a
//! report for another version is refused, so the vehicle flies one version or the next, never a
//! mix.
//!
//! By concern: `types` holds what goes in and out (commands' errors, events, telemetry, the
//! state snapshot); this file the [`Executive`] itself, its queries and the vehicle's reports;
//! `commands` the in-flight commands; `cursor` how the cursor walks the plan (frames, legs,
//! holds, loops, emergency rules); `tree` finding nodes in the plan; [`expand_nominal`] the
//! waypoint stream with no in-flight change. The executive flies only checked plans
//! ([`crate::check`]), and checks each change to its plan the same way.

mod commands;
mod cursor;
mod nominal;
mod tree;
mod types;

pub use commands::nearest_neighbour;
pub use nominal::expand_nominal;
pub(crate) use types::flight_events;
pub use types::{
    CommandError, Event, EventKind, ExecState, ExpandError, HoldHere, RetaskMode, Telemetry,
};

use crate::check::CheckedPlan;
use crate::expand::*;
use crate::expr::Value;
use crate::geo::GeoPoint;
use crate::model::*;
use crate::vehicle::VehicleParams;
use cursor::{Active, Frame, FrameKind};
use nominal::SIM_LIMIT;
use std::collections::BTreeMap;
use std::sync::Arc;
use types::*;

/// The run-time executive. See the module docs.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize)]
pub struct Executive {
    #[serde(with = "shared_plan")]
    plan: Arc<FlightPlan>,
    vehicle: VehicleParams,
    version: u64,
    vars: BTreeMap<String, Value>,
    frames: Vec<Frame>,
    active: Option<Active>,
    suspended: Option<Active>,
    next_seq: u64,
    last: Option<Origin>,
    present: Option<GeoPoint>,
    /// The altitude telemetry last reported (an HA hold ends on it, not on its own waypoints'
    /// altitude, which the `alt` variable takes as each waypoint is reached).
    measured_alt: Option<f64>,
    paused: bool,
    completed: bool,
    nominal: bool,
    simulating: bool,
    flown: f64,
    rule_state: Vec<bool>,
    events: Vec<Event>,
    /// The plan's nominal stream, from the check that let the plan in; not persisted (a
    /// restored executive simulates it again when asked).
    #[serde(skip)]
    checked_nominal: Option<Arc<[Waypoint]>>,
}

/// The plan is shared with look-ahead copies; persisted (see `service::persist`) as itself.
mod shared_plan {
    use super::{Arc, FlightPlan};
    use serde::{Deserialize, Deserializer, Serialize, Serializer};

    pub fn serialize<S: Serializer>(p: &Arc<FlightPlan>, s: S) -> Result<S::Ok, S::Error> {
        p.as_ref().serialize(s)
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Arc<FlightPlan>, D::Error> {
        FlightPlan::deserialize(d).map(Arc::new)
    }
}

impl Executive {
    /// An executive at the start of a checked plan (version 1), for the vehicle it was checked
    /// for.
    pub fn from_checked(checked: CheckedPlan) -> Self {
        let (plan, vehicle, nominal) = checked.into_parts();
        let mut ex = Self::new(plan, vehicle);
        ex.checked_nominal = Some(nominal);
        ex
    }

    /// An executive at the start of `plan` (version 1), which must have passed the check for
    /// `vehicle`: the simulations of [`crate::check`] itself.
    pub(crate) fn new(plan: impl Into<Arc<FlightPlan>>, vehicle: VehicleParams) -> Self {
        let mut ex = Self {
            plan: plan.into(),
            vehicle,
            version: 1,
            vars: BTreeMap::new(),
            frames: Vec::new(),
            active: None,
            suspended: None,
            next_seq: 0,
            last: None,
            present: None,
            measured_alt: None,
            paused: false,
            completed: false,
            nominal: false,
            simulating: false,
            flown: 0.0,
            rule_state: Vec::new(),
            events: Vec::new(),
            checked_nominal: None,
        };
        ex.start();
        ex
    }

    fn start(&mut self) {
        for b in ["alt", "ground_speed", "elapsed_s"] {
            self.vars.entry(b.to_string()).or_insert(Value::Number(0.0));
        }
        self.vars
            .entry("battery".into())
            .or_insert(Value::Number(100.0));
        for v in &self.plan.variables {
            self.vars.insert(v.name.clone(), v.init);
        }
        self.frames.clear();
        self.active = None;
        self.suspended = None;
        self.completed = false;
        self.flown = 0.0;
        match Stage::ALL
            .into_iter()
            .find(|s| !self.plan.stage(*s).is_empty())
        {
            Some(s) => {
                self.frames.push(Frame {
                    index: 0,
                    kind: FrameKind::Stage(s),
                });
                self.emit(EventKind::StageChanged { stage: s });
            }
            None => self.finish(),
        }
        self.rule_state = self
            .plan
            .emergencies
            .iter()
            .map(|r| r.on.holds(&|n| self.var(n)))
            .collect();
        self.settle();
    }

    // ----- queries -------------------------------------------------------------------------

    /// The current plan version (starts at 1, increases with every plan change).
    pub fn version(&self) -> u64 {
        self.version
    }

    /// The plan being flown.
    pub fn plan(&self) -> &FlightPlan {
        &self.plan
    }

    /// The plan's nominal waypoint stream (as [`expand_nominal`] gives it): the one its check
    /// flew, simulated again only for an executive restored from a saved state.
    pub fn nominal(&self) -> Arc<[Waypoint]> {
        match &self.checked_nominal {
            Some(n) => Arc::clone(n),
            None => expand_nominal(Arc::clone(&self.plan), self.vehicle.clone())
                .map(Arc::from)
                .unwrap_or_else(|_| Arc::from(Vec::new())),
        }
    }

    /// The next `n` waypoints, each with its sequence number and the plan version; empty when
    /// paused or completed. Computed from the present state, so it reflects every change.
    pub fn next_waypoints(&self, n: usize) -> Vec<Waypoint> {
        if self.paused || self.completed {
            return Vec::new();
        }
        let mut sim = self.sim_copy();
        // `n` may be far more than the plan holds: grow as waypoints come.
        let mut out = Vec::with_capacity(n.min(64));
        for k in 0..n {
            let Some(w) = sim.head() else { break };
            let mut w = w.clone();
            w.seq = self.next_seq + k as u64;
            w.version = self.version;
            out.push(w);
            sim.reach_head();
        }
        out
    }

    /// Events since the last call, oldest first.
    pub fn take_events(&mut self) -> Vec<Event> {
        std::mem::take(&mut self.events)
    }

    /// A snapshot for stations.
    pub fn state(&self) -> ExecState {
        let mut loops = Vec::new();
        self.walk_frames(|node, kind| {
            if let FrameKind::Loop { iteration, .. } = kind {
                loops.push((node.id.clone(), *iteration));
            }
        });
        ExecState {
            version: self.version,
            plan: self.plan.name.clone(),
            stage: self.stage(),
            leg: self.active.as_ref().map(|a| a.id.clone()),
            next_seq: self.next_seq,
            paused: self.paused,
            completed: self.completed,
            holding: self.active.as_ref().is_some_and(|a| a.hold.is_some()),
            loops,
            vars: self.vars.clone(),
        }
    }

    /// Progress by distance: flown / (flown + remaining nominal distance), 1 when completed.
    pub fn progress(&self) -> f64 {
        let (flown, remaining) = self.distances();
        if self.completed {
            return 1.0;
        }
        if flown + remaining <= 0.0 {
            return 0.0;
        }
        flown / (flown + remaining)
    }

    /// Metres flown in this plan version and metres left in the nominal continuation (what
    /// [`Self::progress`] divides).
    pub fn distances_m(&self) -> (f64, f64) {
        self.distances()
    }

    /// Metres left to fly nominally, `(plan, current leg)`, from the present position when
    /// it is known (the part of the way to the target already covered is taken off); the
    /// current leg is the target waypoint's. What an ETA divides by a speed.
    pub fn remaining_m(&self) -> (f64, f64) {
        let mut sim = self.sim_copy();
        sim.nominal = true;
        sim.paused = false;
        let Some(leg) = sim.head().map(|w| w.leg.clone()) else {
            return (0.0, 0.0);
        };
        let covered = match (self.present, self.last, sim.head()) {
            (Some(p), Some(l), Some(h)) => {
                (crate::geo::distance(l.pos, h.pos()) - crate::geo::distance(p, h.pos())).max(0.0)
            }
            _ => 0.0,
        };
        let start = sim.flown;
        let mut leg_m = None;
        let mut steps = 0;
        while let Some(h) = sim.head() {
            if steps >= SIM_LIMIT {
                break;
            }
            if leg_m.is_none() && h.leg != leg {
                leg_m = Some(sim.flown - start);
            }
            sim.reach_head();
            steps += 1;
        }
        let plan_m = sim.flown - start;
        let leg_m = leg_m.unwrap_or(plan_m);
        ((plan_m - covered).max(0.0), (leg_m - covered).max(0.0))
    }

    /// Numbers the waypoints from `seq` on, when that is above the next sequence number. A
    /// service calls it after handing waypoints to a queue it cannot take back (the VAS keeps
    /// driving to its target after "clear"), so a late report for one of them is not taken
    /// for the new waypoint with the same number. Nothing else changes.
    pub fn skip_seqs_to(&mut self, seq: u64) {
        self.next_seq = self.next_seq.max(seq);
    }

    fn distances(&self) -> (f64, f64) {
        let mut sim = self.sim_copy();
        sim.nominal = true;
        sim.paused = false;
        let start = sim.flown;
        let mut steps = 0;
        while sim.head().is_some() && steps < SIM_LIMIT {
            sim.reach_head();
            steps += 1;
        }
        (self.flown, sim.flown - start)
    }

    fn stage(&self) -> Option<Stage> {
        match self.frames.first().map(|f| &f.kind) {
            Some(FrameKind::Stage(s)) => Some(*s),
            _ => None,
        }
    }

    // ----- inputs from the vehicle ----------------------------------------------------------

    /// The vehicle reached waypoint `seq` of plan `version`. Reaching a later waypoint than the
    /// next one passes the ones before.
    ///
    /// # Errors
    /// A stale version, a waypoint already reached, or one beyond the end of the plan.
    pub fn waypoint_reached(&mut self, version: u64, seq: u64) -> Result<(), CommandError> {
        if version != self.version {
            return Err(CommandError::StaleVersion {
                got: version,
                current: self.version,
            });
        }
        if seq < self.next_seq {
            return Err(CommandError::AlreadyReached {
                seq,
                next: self.next_seq,
            });
        }
        // Check first so a refused report changes nothing.
        let ahead = usize::try_from(seq - self.next_seq).unwrap_or(usize::MAX);
        if ahead >= SIM_LIMIT || self.sim_copy().skip_heads(ahead + 1) <= ahead {
            return Err(CommandError::BeyondPlan(seq));
        }
        for _ in 0..=ahead {
            self.reach_head();
        }
        self.emit_progress();
        self.check_rules();
        Ok(())
    }

    /// Telemetry: present position and built-in variables. Emergency rules are checked.
    /// Values that are not finite numbers (and positions off the globe) are ignored.
    pub fn update_telemetry(&mut self, t: Telemetry) {
        if let Some(p) = t.position.filter(|p| check_point("position", *p).is_ok()) {
            self.present = Some(p);
        }
        for (name, v) in [
            ("alt", t.alt),
            ("ground_speed", t.ground_speed),
            ("battery", t.battery),
            ("elapsed_s", t.elapsed_s),
        ] {
            if let Some(v) = v.filter(|v| v.is_finite()) {
                if name == "alt" {
                    self.measured_alt = Some(v);
                }
                self.vars.insert(name.into(), Value::Number(v));
            }
        }
        self.check_rules();
    }
}
